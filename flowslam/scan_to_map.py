"""Scan-to-map registration: LOAM's mapping stage (``mapping:`` config, on by default).

Flow odometry chains scan-to-scan motions, so a small systematic error of every step
adds up. A mapping stage registers each scan's *static* points to a local map of the
recent static points instead, so the error adds up per map, not per scan (A-LOAM's
mapping step; KISS-ICP's whole method).

Frames (all ``T_a_b``, 4x4, m):

- *map frame*: the local map's world. It starts as the backend's world at the first
  mapped scan; scans are put in the map at their registered pose ``T_map_scan``.
- *anchor*: a keyframe whose map pose is fixed; a new one every ``keyframe_distance_m``.
  The factor of scan k is ``T_anchor_k = inv(T_map_anchor) @ T_map_k``: a relative pose
  between two graph variables, so it stays valid when the backend moves its world.

Each step (:meth:`ScanToMap.step`, every ``every``-th scan): the guess ``T_map_k`` is the
last registered scan's map pose times the backend's current motion from that scan to k; the
scan's static points (downsampled to ``source_voxel_m``) are registered to the map by
point-to-plane ICP with a Tukey kernel (Open3D's rule, compiled; the map's KD-tree is kept
until the map changes). Point-to-plane, not KISS-ICP's
point-to-point: on a simulated ``dt`` sequence with exact map poses, point-to-point to a
voxel map was 4-8 cm off (the ground rings, which move with the sensor, pull it back),
point-to-plane 0.3 cm. A result further than ``max_prior_*`` from the guess is not
trusted (no factor; the map restarts at the scan). Every ``insert_every``-th registered
scan (``map_voxel_m``, with normals from its own neighbours) then joins the map; the
others only need their source cloud and are read at every ``source_stride``-th point.
Scans more than ``max_distance_m`` from the newest, or beyond the last ``max_scans`` in
the map, leave it. After a loop closure the backend's
poses move: :meth:`ScanToMap.moved` carries the map rigidly with the latest pose.

The covariance of a factor is the fixed ``rotation_std_deg``/``translation_std_m``
(rotation first, as GTSAM's Pose3 tangent).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from flowslam import geometry
from flowslam.config.mapping import MappingConfig

__all__ = ["LocalMap", "MapFactor", "ScanToMap"]


@dataclass
class MapFactor:
    """The measurement of one registered scan: ``T_anchor_scan`` (4x4, maps scan points
    into the anchor's sensor frame, m) with its 6x6 covariance (rotation first)."""

    anchor: int
    scan: int
    T_anchor_scan: np.ndarray
    covariance: np.ndarray


@dataclass
class MappingStats:
    """Counts and per-step wall times of the stage (``run.json`` ``mapping``)."""

    factors: int = 0
    restarts: int = 0
    keyframes: int = 0
    skipped: int = 0
    """Scans with fewer than ``min_points`` usable points."""
    seconds: list = field(default_factory=list)

    def as_dict(self) -> dict:
        ms = np.asarray(self.seconds) * 1e3
        return {"factors": self.factors, "restarts": self.restarts, "keyframes": self.keyframes,
                "skipped": self.skipped, "steps": len(ms),
                "median_ms": float(np.median(ms)) if len(ms) else None,
                "mean_ms": float(np.mean(ms)) if len(ms) else None,
                "p95_ms": float(np.percentile(ms, 95)) if len(ms) else None}


class LocalMap:
    """The last scans put in the map: points and normals (oriented towards their sensor)
    in the map frame (m)."""

    def __init__(self, max_scans: int, max_distance_m: float, voxel_m: float):
        self.max_distance_m, self.voxel_m = max_distance_m, voxel_m
        self._scans: deque = deque(maxlen=max_scans)
        """(points (N,3), normals (N,3), sensor position (3,)), map frame."""
        self._cloud = self._target = None

    def __len__(self) -> int:
        return len(self._scans)

    def clear(self) -> None:
        self._scans.clear()
        self._cloud = self._target = None

    def add(self, points: np.ndarray, normals: np.ndarray, T_map_scan: np.ndarray) -> None:
        """Add a scan (points and normals in its sensor frame) at ``T_map_scan``; scans
        farther than ``max_distance_m`` from it leave."""
        R, t = T_map_scan[:3, :3], T_map_scan[:3, 3]
        self._scans.append((points @ R.T + t, normals @ R.T, t.copy()))
        while np.linalg.norm(self._scans[0][2] - t) > self.max_distance_m:
            self._scans.popleft()
        self._cloud = self._target = None

    def moved(self, C: np.ndarray) -> None:
        """Apply ``C`` (4x4, old map frame -> new) to every scan."""
        R, t = C[:3, :3], C[:3, 3]
        self._scans = deque(((p @ R.T + t, n @ R.T, R @ o + t) for p, n, o in self._scans),
                            maxlen=self._scans.maxlen)
        self._cloud = self._target = None

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """The map downsampled to ``voxel_m`` (the scans overlap: one point, the mean, per
        voxel) as (points (M,3), unit normals (M,3)), map frame, cached until it changes:
        Open3D's ``voxel_down_sample`` of the points with their normals, then
        ``normalize_normals`` (the same numbers, compiled:
        :func:`flowslam.compiled_voxels.open3d_voxel_means`; voxels in key order)."""
        from flowslam.compiled_voxels import open3d_voxel_means

        if self._cloud is None:
            points, normals = open3d_voxel_means(np.concatenate([s[0] for s in self._scans]), self.voxel_m,
                                                 normals=np.concatenate([s[1] for s in self._scans]))
            squared = normals[:, 0] ** 2 + normals[:, 1] ** 2 + normals[:, 2] ** 2
            normals[squared > 0] /= np.sqrt(squared[squared > 0])[:, None]  # Eigen's normalize()
            self._cloud = points, normals
        return self._cloud

    def target(self):
        """(:class:`~flowslam.sceneflow.refinement.compiled_icp.IcpTarget` of the :meth:`cloud`'s
        points, their unit normals (M,3)): the registration's target, its KD-tree built once
        per map (the map changes every ``insert_every`` scans, the registration runs every scan)."""
        from flowslam.sceneflow.refinement.compiled_icp import IcpTarget

        if self._target is None:
            points, normals = self.cloud()
            self._target = IcpTarget(points), normals
        return self._target


class ScanToMap:
    """The local map and the registration to it (module doc). One per sequence."""

    def __init__(self, config: MappingConfig | None = None):
        self.config = c = config or MappingConfig()
        self.map = LocalMap(c.max_scans, c.max_distance_m, c.map_voxel_m)
        self._covariance = geometry.pose_covariance(np.deg2rad(c.rotation_std_deg), c.translation_std_m)
        self._anchor: tuple[int, np.ndarray] | None = None
        """(index, T_map_anchor): the factors' first scan."""
        self._last: tuple[int, np.ndarray] | None = None
        """(index, T_map_scan) of the last registered scan (in the map or not): the guess
        starts there."""
        self._steps = 0
        self._registered = 0
        """Registered scans since the last one put in the map."""
        self.stats = MappingStats()

    def step(self, index: int, points: np.ndarray, static_mask: np.ndarray | None,
             estimate: Callable[[int], np.ndarray]) -> MapFactor | None:
        """Register scan ``index`` and add it to the map. ``points`` (N,3) sensor frame;
        ``static_mask`` (N,) bool or None (all static); ``estimate(i)`` the backend's
        current ``T_world_sensor`` of an added scan. Returns the factor to add, or None
        (also on the scans that ``every`` skips, which cost nothing)."""
        self._steps += 1
        if (self._steps - 1) % self.config.every:
            return None
        start = time.perf_counter()
        try:
            return self._step(index, points, static_mask, estimate)
        finally:
            self.stats.seconds.append(time.perf_counter() - start)

    def moved(self, T_world_latest_before: np.ndarray, T_world_latest_after: np.ndarray) -> None:
        """The backend moved its poses (a loop closure): carry the map and the anchor with
        the latest scan's correction ``after @ inv(before)`` (world frame)."""
        if self._anchor is None:
            return
        C = geometry.orthonormalized(np.asarray(T_world_latest_after) @ geometry.inv(T_world_latest_before))
        self.map.moved(C)
        self._anchor = (self._anchor[0], C @ self._anchor[1])
        self._last = (self._last[0], C @ self._last[1])

    # ------------------------------------------------------------------------------

    def _prepare(self, points: np.ndarray, static_mask: np.ndarray | None, stride: int = 1) -> np.ndarray:
        """Static points in range (every ``stride``-th of them), downsampled to
        ``map_voxel_m``: (M,3) voxel centroids, sensor frame (Open3D's ``voxel_down_sample``
        numbers, compiled: :func:`flowslam.compiled_voxels.open3d_voxel_means`)."""
        from flowslam.compiled_voxels import open3d_voxel_means

        c = self.config
        p = np.asarray(points)[::stride]
        r2 = np.einsum("ij,ij->i", p, p)  # in the input's precision: float32 scans stay float32 here
        keep = (r2 >= c.min_range_m**2) & (r2 <= c.max_range_m**2)
        if static_mask is not None:
            keep &= np.asarray(static_mask, dtype=bool)[::stride]
        # voxel means: KISS-ICP's one-point-per-voxel downsampling here made the dt 300 drift
        # 2x worse (0.043 % vs 0.022 %)
        return open3d_voxel_means(p, c.map_voxel_m, keep)[0]

    def _maps_next(self) -> bool:
        """Whether the next scan goes into the map: every ``insert_every``-th registered
        scan, and every scan while there is no map or it is warming up."""
        c = self.config
        return self._anchor is None or len(self.map) < c.warmup_scans or self._registered + 1 >= c.insert_every

    def _insert(self, cloud: np.ndarray, T_map_scan: np.ndarray, index: int, into_map: bool) -> None:
        """Make scan ``index`` (its :meth:`_prepare` points ``cloud``, at ``T_map_scan``) the
        guess's start and, if ``into_map``, put it in the map, with normals from its own
        neighbours (Open3D) oriented towards the sensor (so that averages in the map agree)."""
        import open3d as o3d

        self._last = (index, T_map_scan)
        self._registered += 1
        if not into_map:
            return
        scan = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        scan.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4.0 * self.config.map_voxel_m, max_nn=10))
        scan.orient_normals_towards_camera_location(np.zeros(3))
        self.map.add(np.asarray(scan.points), np.asarray(scan.normals), T_map_scan)
        self._registered = 0

    def _restart(self, index: int, cloud: np.ndarray, T_world_scan: np.ndarray) -> None:
        """A new map (frame = the backend's world now) holding this scan, its anchor."""
        self.map.clear()
        self._anchor = (index, T_world_scan)
        self._insert(cloud, T_world_scan, index, into_map=True)
        self.stats.keyframes += 1

    def _register(self, cloud: np.ndarray, guess: np.ndarray) -> np.ndarray:
        """``T_map_scan`` of the scan's :meth:`_prepare` points ``cloud`` (sensor frame),
        downsampled again to ``source_voxel_m``, from ``guess``: point-to-plane
        ICP with a Tukey kernel onto the map (Open3D's ``registration_icp`` rule, compiled:
        :func:`~flowslam.sceneflow.refinement.compiled_icp.register_point_to_plane`, on the
        map's KD-tree kept while the map is unchanged)."""
        from flowslam.compiled_voxels import open3d_voxel_means
        from flowslam.sceneflow.refinement.compiled_icp import register_point_to_plane

        c = self.config
        source = open3d_voxel_means(cloud, c.source_voxel_m)[0]
        target, normals = self.map.target()
        T = register_point_to_plane(source, target, normals, guess, [c.max_correspondence_m], c.max_iterations,
                                    1e-4, 1e-4, kernel=c.kernel_m)
        return geometry.orthonormalized(T)

    def _step(self, index, points, static_mask, estimate) -> MapFactor | None:
        c = self.config
        into_map = self._maps_next()
        # a scan that only gets registered is read at source_stride: its source cloud is
        # all it needs
        cloud = self._prepare(points, static_mask, 1 if into_map else c.source_stride)
        if len(cloud) < c.min_points:
            self.stats.skipped += 1
            return None
        T_world_scan = geometry.orthonormalized(estimate(index))
        if self._anchor is None:
            self._restart(index, cloud, T_world_scan)
            return None
        anchor, T_map_anchor = self._anchor
        last, T_map_last = self._last
        guess = geometry.orthonormalized(T_map_last @ geometry.relative(estimate(last), T_world_scan))
        if len(self.map) < c.warmup_scans:  # the map holds too little to register to yet
            self._insert(cloud, guess, index, into_map)
            return None
        T_map_scan = self._register(cloud, guess)
        xi = geometry.log_se3(geometry.inv(guess) @ T_map_scan)
        if (np.rad2deg(np.linalg.norm(xi[:3])) > c.max_prior_rotation_deg
                or np.linalg.norm(xi[3:]) > c.max_prior_translation_m):
            self.stats.restarts += 1
            self._restart(index, cloud if into_map else self._prepare(points, static_mask), T_world_scan)
            return None
        self._insert(cloud, T_map_scan, index, into_map)
        factor = MapFactor(anchor, index, geometry.relative(T_map_anchor, T_map_scan), self._covariance.copy())
        self.stats.factors += 1
        if np.linalg.norm(T_map_scan[:3, 3] - T_map_anchor[:3, 3]) > c.keyframe_distance_m:
            self._anchor = (index, T_map_scan)
            self.stats.keyframes += 1
        return factor
