"""The result of the traffic simulation: ``Actor`` (one moving actor's pose track) and
``ActorSet`` (all actors, their shape library and the simulation time steps).

Frames and units: poses are planar, in the town frame (metres, radians): ``x, y`` is the
footprint centre on the ground, ``yaw`` the heading of the actor's local x axis (forward);
``times`` are seconds on the frames' time axis, one per simulation step (``DT`` apart),
and poses are interpolated linearly in between.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flowslam.simulation.meshes import ActorShape
from flowslam.simulation.paths import PoseTrack


@dataclass
class Actor:
    id: int
    """Instance id (``labels.ACTOR_ID_BASE + k``)."""
    kind: str
    """"vehicle", "walker", "crosser", "convoy" or "oncoming"."""
    shape: int
    track: PoseTrack
    alive: np.ndarray
    """(S,) bool per simulation step."""


@dataclass
class ActorSet:
    actors: list[Actor]
    shapes: list[ActorShape]
    times: np.ndarray
    removed: int = 0
    stats: dict = field(default_factory=dict)

    def count_by(self, what: str = "shape") -> dict:
        """Actors per shape kind (car, truck, cyclist, pedestrian) or per role (``what="role"``)."""
        out: dict = {}
        for a in self.actors:
            key = self.shapes[a.shape].kind if what == "shape" else a.kind
            out[key] = out.get(key, 0) + 1
        return out
