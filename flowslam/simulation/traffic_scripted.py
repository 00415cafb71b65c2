"""The scripted side of the traffic: pose tracks of the ego's convoy and of the oncoming
stream (``scripted_tracks``; they yield to nobody), and ``EgoGroup``, the footprint
centres of the ego and those scripted actors at every step, which the other actors'
right-of-way decisions and the final overlap check query.

Town frame, metres, radians; times in seconds on the simulation steps (``DT`` apart).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation.ego_path import EgoMotion
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.traffic_spec import DT, TrafficSpec


def scripted_tracks(ego: EgoMotion, spec: TrafficSpec, times: np.ndarray) -> list[tuple[str, PoseTrack]]:
    """Pose tracks of the convoy and of the oncoming stream (scripted, they yield to nobody)."""
    out = []
    s = ego.s_at(times)
    for d in spec.convoy:
        p, h = ego.route.position(s + d), ego.route.heading(s + d)
        out.append(("convoy", PoseTrack(times, p[:, 0], p[:, 1], h)))
    if spec.oncoming and ego.oncoming_route is not None:
        for i in range(spec.oncoming):
            sr = ego.oncoming_s.at(times - i * spec.oncoming_headway)[0]
            p, h = ego.oncoming_route.position(sr), ego.oncoming_route.heading(sr)
            out.append(("oncoming", PoseTrack(times, p[:, 0], p[:, 1], h)))
    return out


class EgoGroup:
    """Footprint centres of the ego, its convoy and the oncoming stream at every step."""

    def __init__(self, ego: EgoMotion, times: np.ndarray, scripted: list, radius: float):
        fx, fy, self.ego_yaw = ego.footprint_at(times)
        centers = [np.stack([fx, fy], axis=1)] + [np.stack([tr.x, tr.y], axis=1) for _, tr in scripted]
        self.centers = np.stack(centers, axis=1)  # (S, G, 2); member 0 is the ego
        self.radius = radius
        self.times = times

    def clear(self, tree: cKDTree, t0: float, t1: float, extra: float) -> bool:
        """True if no member comes within ``radius + extra`` of the points in ``tree``
        between ``t0`` and ``t1``."""
        i0 = max(int(np.floor((t0 - self.times[0]) / DT)), 0)
        i1 = min(int(np.ceil((t1 - self.times[0]) / DT)) + 1, len(self.times))
        if i1 <= i0:
            return True
        pts = self.centers[i0:i1].reshape(-1, 2)
        d, _ = tree.query(pts, distance_upper_bound=self.radius + extra)
        return not np.isfinite(d).any()

    def distance(self, p: np.ndarray, i: int) -> float:
        """Distance from ``p`` to the nearest member at step ``i``."""
        return float(np.min(np.linalg.norm(self.centers[min(i, len(self.times) - 1)] - p, axis=1)))
