"""``ScanContextLoopCloser``: the ``LoopCloser`` of the ``s-loam`` variant.

Per scan ``j`` (``add_scan``):

1. Scan Context descriptor and ring key of the scan (sensor frame);
2. the ``num_candidates`` nearest ring keys among the eligible earlier scans
   (:class:`~flowslam.loop_closure.candidates.CandidateIndex`: not among the last
   N scans nor the last M metres of path);
3. the column-shift distance to each; the best one, if below ``distance_threshold``,
   is verified by ICP (:func:`~flowslam.loop_closure.verification.verify`) started
   from the descriptor's yaw;
4. an accepted pair becomes a :class:`~flowslam.interfaces.LoopClosure`
   ``(i, j, T_i_j, covariance)`` and is logged with its fitness, RMSE and the
   *correction*: how far ``T_i_j`` is from the current estimate
   ``inv(T_world_i) @ T_world_j`` (m and deg).

Memory per old scan: the descriptor (rings x sectors, kept as float16: 2.4 kB at
20 x 60), its ring key (float64), the pose and the path length, about 3 kB in all.
The voxel-downsampled cloud used for verification (int16 centimetres, about 25 kB
for KITTI at 0.75 m voxels) goes to a spill file (:class:`~.verification.CloudStore`)
and is read back only when the scan is a candidate to verify.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from flowslam import geometry
from flowslam.interfaces import LoopClosure

from . import scan_context as sc
from .candidates import CandidateIndex
from flowslam.config.loop_closure import LoopClosureConfig
from .verification import CloudStore, CompactCloud, downsample, verify

log = logging.getLogger(__name__)

__all__ = ["ScanContextLoopCloser", "DetectorStats"]


@dataclass
class DetectorStats:
    """Counters and per-scan timings (s) of the loop closer."""

    scans: int = 0
    descriptor_hits: int = 0
    """Scans whose best candidate was below ``distance_threshold`` (and got verified)."""
    accepted: int = 0
    rejected: int = 0
    seconds_per_scan: list[float] = field(default_factory=list)
    """Descriptor + storage + search (+ verification when one ran)."""
    seconds_verification: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        per_scan = np.asarray(self.seconds_per_scan) * 1e3
        ver = np.asarray(self.seconds_verification) * 1e3
        return {
            "scans": self.scans,
            "verified": self.descriptor_hits,
            "accepted": self.accepted,
            "rejected": self.rejected,
            "median_ms_per_scan": float(np.median(per_scan)) if len(per_scan) else None,
            "median_ms_verification": float(np.median(ver)) if len(ver) else None,
            "max_ms_verification": float(np.max(ver)) if len(ver) else None,
        }


class ScanContextLoopCloser:
    """Scan Context place recognition + ICP verification (see module doc)."""

    def __init__(self, config: LoopClosureConfig | None = None):
        self.config = config or LoopClosureConfig()
        c = self.config
        self._candidates = CandidateIndex(c.exclude_recent_frames, c.exclude_recent_m, c.tree_rebuild_every)
        self._indices: list[int] = []
        self._descriptors: list[np.ndarray] = []
        self._poses: list[np.ndarray] = []
        self._clouds = CloudStore()
        self._path_m = 0.0
        self._path_at: list[float] = []  # path length (m) travelled up to each stored scan
        self._last_accepted_at = -(10**9)
        self.loops: list[LoopClosure] = []
        """Every accepted loop, in order."""
        self.stats = DetectorStats()

    def __len__(self) -> int:
        return len(self._indices)

    def memory_bytes(self) -> int:
        """Bytes held in memory for the scans so far (descriptors, poses, ring keys, the
        cloud store's index and any cloud it could not spill)."""
        desc = sum(d.nbytes for d in self._descriptors)
        return desc + self._clouds.nbytes + len(self._poses) * (128 + 8 * self.config.scan_context.rings)

    def disk_bytes(self) -> int:
        """Bytes of verification clouds in the spill file."""
        return self._clouds.disk_bytes

    def add_scan(self, index: int, points: np.ndarray, T_world_sensor: np.ndarray) -> list[LoopClosure]:
        """Add scan ``index`` (points (N,3), sensor frame, m; its current ``T_world_sensor``);
        return the verified loop it closes with an earlier scan (a list of 0 or 1)."""
        start = time.perf_counter()
        c = self.config
        T_world_sensor = np.asarray(T_world_sensor, dtype=np.float64)
        if self._poses:
            self._path_m += float(np.linalg.norm(T_world_sensor[:3, 3] - self._poses[-1][:3, 3]))
        desc = sc.scan_context(points, c.scan_context)
        cloud = downsample(points, c.verification, seed=index)
        self._indices.append(int(index))
        self._descriptors.append(desc.astype(np.float16))
        self._poses.append(T_world_sensor.copy())
        self._path_at.append(self._path_m)
        self._clouds.append(CompactCloud(cloud))
        self._candidates.add(sc.ring_key(desc), self._path_m)
        self.stats.scans += 1
        position = len(self._indices) - 1

        loops: list[LoopClosure] = []
        if position - self._last_accepted_at > c.cooldown_frames:
            loop = self._detect(position, desc, cloud)
            if loop is not None:
                loops.append(loop)
        self.stats.seconds_per_scan.append(time.perf_counter() - start)
        return loops

    def _distance(self, a: int, b: int) -> float:
        return float(np.linalg.norm(self._poses[a][:3, 3] - self._poses[b][:3, 3]))

    def _within_gate(self, cand: int, position: int, metres: float) -> bool:
        """``metres`` (a distance or a correction) is within the drift gate of the pair."""
        c = self.config
        travelled = self._path_at[position] - self._path_at[cand]
        return metres <= c.gate_base_m + c.gate_drift_fraction * travelled

    def _detect(self, position: int, desc: np.ndarray, cloud: np.ndarray) -> LoopClosure | None:
        c = self.config
        found = self._candidates.query(sc.ring_key(desc), c.num_candidates)
        found = [p for p in found if self._within_gate(int(p), position, self._distance(int(p), position))]
        if len(found) == 0:
            return None
        dists, shifts = sc.distances(desc, np.stack([self._descriptors[p] for p in found]))
        best = int(np.argmin(dists))
        cand, dist = int(found[best]), float(dists[best])
        if dist > c.distance_threshold:
            return None
        self.stats.descriptor_hits += 1
        i, j = self._indices[cand], self._indices[position]
        # distances(query=j, candidates=i) gives the yaw of T_j_i; the ICP guess is T_i_j.
        yaw = -sc.shift_to_yaw(int(shifts[best]), c.scan_context.sectors)
        t0 = time.perf_counter()
        result = verify(cloud, self._clouds.points(cand), geometry.from_euler("z", yaw), c.verification)
        self.stats.seconds_verification.append(time.perf_counter() - t0)
        if not result.accepted:
            self.stats.rejected += 1
            log.debug("loop %d-%d rejected: %s (descriptor %.3f)", i, j, result.reason, dist)
            return None

        T_i_j_est = geometry.relative(self._poses[cand], self._poses[position])
        correction = geometry.inv(T_i_j_est) @ result.T_target_source
        correction_m = float(geometry.translation_norm(correction))
        correction_deg = float(np.rad2deg(geometry.rotation_angle(correction)))
        if not self._within_gate(cand, position, correction_m):
            self.stats.rejected += 1
            log.debug("loop %d-%d rejected: correction %.1f m outside the drift gate", i, j, correction_m)
            return None
        loop = LoopClosure(
            i=i,
            j=j,
            T_i_j=result.T_target_source,
            covariance=result.covariance,
            fitness=result.fitness,
            inlier_rmse=result.inlier_rmse,
            descriptor_distance=dist,
            info={
                "yaw_init_deg": float(np.rad2deg(yaw)),
                "correction_m": correction_m,
                "correction_deg": correction_deg,
                "verification_ms": self.stats.seconds_verification[-1] * 1e3,
            },
        )
        self.stats.accepted += 1
        self._last_accepted_at = position
        self.loops.append(loop)
        log.info(
            "loop closure %d-%d: fitness %.3f, RMSE %.3f m, descriptor %.3f, correction %.2f m / %.2f deg",
            i, j, result.fitness, result.inlier_rmse, dist, correction_m, correction_deg,
        )
        return loop
