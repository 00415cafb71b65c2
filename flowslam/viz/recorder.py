"""Write what a run saw into a rerun ``.rrd`` file: one entity per kind of thing, one timeline.

Everything is logged in the **world frame** (``T_world_sensor``'s world: the first
processed scan's sensor frame; metres, z up for LiDAR data) on the sequence timeline
``frame`` (= scan index). Entity paths (:data:`ENTITIES`):

- ``world/scan``: the scan's points at its pose, ``class_ids`` 0 unlabelled, 1 static,
  2 dynamic (an annotation context gives the colours and names);
- ``world/flow``: ego-motion-compensated scene flow on a subsample (arrows, m per scan step);
- ``world/objects``: boxes of the moving instances (label = track id) and
  ``world/objects/velocity``: arrows of 1 s of travel (m/s);
- ``world/trajectory/estimate``, ``world/trajectory/gt``: the path up to the frame;
  ``world/trajectory/final``: the final (optimised) estimate, static;
- ``world/sensor``: the sensor pose (transform + axes);
- ``world/loops``: loop closures (a segment between the two scans' positions);
- ``world/static_map``, ``world/dynamic_points``: the maps of the results folder, static.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from flowslam import geometry
from flowslam.viz import import_rerun

__all__ = ["RerunRecorder", "ENTITIES", "TIMELINE", "UNLABELLED", "STATIC", "DYNAMIC", "boxes_of_instances"]

TIMELINE = "frame"
UNLABELLED, STATIC, DYNAMIC = 0, 1, 2
CLASSES = ((UNLABELLED, "unlabelled", (170, 170, 170)), (STATIC, "static", (80, 135, 215)),
           (DYNAMIC, "dynamic", (240, 50, 50)))
ENTITIES = {
    "scan": "world/scan", "flow": "world/flow", "objects": "world/objects",
    "velocity": "world/objects/velocity", "estimate": "world/trajectory/estimate",
    "gt": "world/trajectory/gt", "final": "world/trajectory/final", "sensor": "world/sensor",
    "loops": "world/loops", "static_map": "world/static_map", "dynamic_points": "world/dynamic_points",
}
MAX_PATH_VERTICES = 1000
"""Longer paths are logged with a stride (the data per frame stays bounded)."""


def boxes_of_instances(points: np.ndarray, instance_ids: np.ndarray, ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes (in the points' frame) of each instance in ``ids``: (K,3) centres
    and (K,3) half sizes (m); an id without points gets a zero box at the origin."""
    centres, halves = np.zeros((len(ids), 3)), np.zeros((len(ids), 3))
    for k, i in enumerate(ids):
        own = points[instance_ids == i]
        if len(own):
            lo, hi = own.min(axis=0), own.max(axis=0)
            centres[k], halves[k] = (lo + hi) / 2, np.maximum((hi - lo) / 2, 0.05)
    return centres, halves


def _track_colours(track_ids: Sequence[int]) -> np.ndarray:
    """A stable colour per track id (any int), (K,3) uint8."""
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    return (np.array([cmap((i * 7) % 20)[:3] for i in track_ids]).reshape(-1, 3) * 255).astype(np.uint8)


def _strided(positions: np.ndarray) -> np.ndarray:
    if len(positions) <= MAX_PATH_VERTICES:
        return positions
    keep = np.unique(np.r_[np.linspace(0, len(positions) - 1, MAX_PATH_VERTICES).astype(int), len(positions) - 1])
    return positions[keep]


class RerunRecorder:
    """An ``.rrd`` file being written (module doc for entities and frames).

    Args:
        path: the ``.rrd`` file (its folder is created).
        max_scan_points: points per logged scan at most (a fixed-seed subsample; keeps
            the file a few MB per 10 scans).
        max_flow_arrows: flow arrows per scan at most (dynamic points first).
    """

    def __init__(self, path: str | Path, *, max_scan_points: int = 30000, max_flow_arrows: int = 1500,
                 application_id: str = "flowslam"):
        self.rr = import_rerun()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_scan_points, self.max_flow_arrows = max_scan_points, max_flow_arrows
        self._rng = np.random.default_rng(0)
        self.stream = self.rr.RecordingStream(application_id)
        self.stream.save(str(self.path))
        rr = self.rr
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.stream.log(ENTITIES["scan"], rr.AnnotationContext(list(CLASSES)), static=True)
        self._estimate: list[np.ndarray] = []
        self._gt: list[np.ndarray] = []
        self._positions: dict[int, np.ndarray] = {}
        self._loops: list[np.ndarray] = []

    def at(self, index: int) -> None:
        """Log what follows at scan ``index`` of the ``frame`` timeline."""
        self.stream.set_time(TIMELINE, sequence=int(index))

    def _subsample(self, n: int, cap: int, first: np.ndarray | None = None) -> np.ndarray:
        """Up to ``cap`` of ``range(n)``, sorted; the indices in ``first`` are taken first."""
        if n <= cap:
            return np.arange(n)
        first = np.zeros(0, dtype=int) if first is None else np.asarray(first, dtype=int)[:cap]
        rest = np.setdiff1d(np.arange(n), first)
        more = self._rng.choice(rest, size=cap - len(first), replace=False) if cap > len(first) else []
        return np.sort(np.r_[first, more]).astype(int)

    # -- per frame -----------------------------------------------------------------------

    def pose(self, index: int, T_world_sensor: np.ndarray, T_world_gt: np.ndarray | None = None) -> None:
        """The sensor pose of scan ``index`` and the paths so far (estimate, GT if given)."""
        rr = self.rr
        T = np.asarray(T_world_sensor, dtype=np.float64)
        self.at(index)
        self._positions[int(index)] = T[:3, 3].copy()
        self._estimate.append(T[:3, 3].copy())
        self.stream.log(ENTITIES["sensor"], rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]),
                        rr.TransformAxes3D(2.0))
        self.stream.log(ENTITIES["estimate"], rr.LineStrips3D([_strided(np.array(self._estimate))],
                                                                colors=[(40, 200, 120)], radii=0.08))
        if T_world_gt is not None:
            self._gt.append(np.asarray(T_world_gt, dtype=np.float64)[:3, 3].copy())
            self.stream.log(ENTITIES["gt"], rr.LineStrips3D([_strided(np.array(self._gt))],
                                                              colors=[(120, 120, 120)], radii=0.06))

    def scan(self, index: int, T_world_sensor: np.ndarray, points: np.ndarray,
             labels: np.ndarray | None = None) -> None:
        """Scan ``index``'s ``points`` (N,3, sensor frame) at its pose; ``labels`` (N,)
        :data:`STATIC`/:data:`DYNAMIC`/:data:`UNLABELLED` (None: all unlabelled). A later
        call for the same scan replaces the earlier one."""
        points = np.asarray(points, dtype=np.float64)
        labels = np.full(len(points), UNLABELLED, dtype=np.uint16) if labels is None else labels.astype(np.uint16)
        keep = self._subsample(len(points), self.max_scan_points, np.flatnonzero(labels == DYNAMIC))
        world = geometry.transform_points(T_world_sensor, points[keep]).astype(np.float32)
        self.at(index)
        self.stream.log(ENTITIES["scan"], self.rr.Points3D(world, class_ids=labels[keep], radii=0.04))

    def flow(self, index: int, origins_world: np.ndarray, vectors_world: np.ndarray,
             dynamic: np.ndarray | None = None) -> None:
        """Flow arrows of scan ``index`` (world frame, m); dynamic points first in the subsample."""
        keep = self._subsample(len(origins_world), self.max_flow_arrows,
                               None if dynamic is None else np.flatnonzero(dynamic))
        self.at(index)
        self.stream.log(ENTITIES["flow"], self.rr.Arrows3D(
            origins=np.asarray(origins_world, np.float32)[keep], vectors=np.asarray(vectors_world, np.float32)[keep],
            colors=[(250, 170, 30)], radii=0.02))

    def objects(self, index: int, centres: np.ndarray, half_sizes: np.ndarray, velocities: np.ndarray,
                track_ids: Sequence[int], quaternions_xyzw: np.ndarray | None = None) -> None:
        """Moving objects of scan ``index``: boxes (world centres, half sizes m, optional
        rotations), velocity arrows (m/s, drawn as 1 s of travel), labelled by track id."""
        rr = self.rr
        ids = [int(i) for i in track_ids]
        speeds = np.linalg.norm(np.asarray(velocities, dtype=np.float64).reshape(-1, 3), axis=1)
        self.at(index)
        box_args = {} if quaternions_xyzw is None else {"quaternions": [rr.Quaternion(xyzw=q) for q in quaternions_xyzw]}
        self.stream.log(ENTITIES["objects"], rr.Boxes3D(
            centers=centres, half_sizes=half_sizes, labels=[f"#{i}" for i in ids], colors=_track_colours(ids),
            **box_args))
        self.stream.log(ENTITIES["velocity"], rr.Arrows3D(
            origins=centres, vectors=velocities, labels=[f"#{i} {s:.1f} m/s" for i, s in zip(ids, speeds)],
            colors=[(255, 230, 0)], radii=0.06))

    def loop(self, index: int, i: int, j: int) -> None:
        """A loop closure between scans ``i`` and ``j`` (both already posed), shown from ``index`` on."""
        if i in self._positions and j in self._positions:
            self._loops.append(np.stack([self._positions[i], self._positions[j]]))
            self.at(index)
            self.stream.log(ENTITIES["loops"], self.rr.LineStrips3D(self._loops, colors=[(230, 30, 200)], radii=0.1))

    # -- whole run -----------------------------------------------------------------------

    def final_trajectory(self, poses: np.ndarray) -> None:
        """The final (optimised) ``T_world_sensor`` of every scan, static."""
        self.stream.log(ENTITIES["final"], self.rr.LineStrips3D([_strided(np.asarray(poses)[:, :3, 3])],
                                                                  colors=[(20, 120, 255)], radii=0.08), static=True)

    def cloud(self, key: str, points_world: np.ndarray, labels: int = STATIC, max_points: int = 500000) -> None:
        """A static cloud (``key`` ``static_map`` or ``dynamic_points``; world frame, m)."""
        points_world = np.asarray(points_world, dtype=np.float32)
        keep = self._subsample(len(points_world), max_points)
        colour = dict((c, rgb) for c, _, rgb in CLASSES)[labels]
        self.stream.log(ENTITIES[key], self.rr.Points3D(points_world[keep], colors=[colour], radii=0.03), static=True)

    def close(self) -> Path:
        """Flush and close the file; returns its path."""
        self.stream.flush()
        self.stream.disconnect()
        return self.path
