"""Geometric verification of a loop candidate: Open3D point-to-plane ICP, coarse to fine.

``verify(source, target, T_init)`` aligns the current scan (source, frame j) to the
earlier one (target, frame i) starting from ``T_init`` (in practice a pure yaw from
the Scan Context column shift) and returns ``T_target_source`` = ``T_i_j``, the
overlap (*fitness*: share of source points with a target neighbour within
``fitness_distance_m``), the inlier RMSE (m), the decision and a 6x6 covariance in
GTSAM's order (rotation rad, translation m; right perturbation ``T_i_j * Exp(xi)``).

Open3D's ``get_information_matrix_from_point_clouds`` is ``sum J^T J`` with
``J = [-hat(q), I]`` for the aligned source points ``q`` in the *target* frame,
i.e. rotation first but the **left** perturbation ``Exp(xi_l) * T`` (checked in
``tests/test_loop_closure.py``). :func:`open3d_information_to_covariance` converts
it: ``xi_l = Ad(T) xi_r``, so ``Sigma_r = Ad(T)^-1 Sigma_l Ad(T)^-T``.

Kept clouds are stored compactly (:class:`CompactCloud`, int16 centimetres); the loop
closer keeps one per scan in a :class:`CloudStore`, which spills them to an unlinked
temporary file (they are read back only to verify a candidate), so that a long run
holds a few bytes per scan in memory for them, not ~25 kB.
"""

from __future__ import annotations

from dataclasses import dataclass

import logging
import os
import tempfile
from array import array

import numpy as np

from flowslam import geometry

from flowslam.config.loop_closure import VerificationConfig

log = logging.getLogger(__name__)

__all__ = [
    "CompactCloud",
    "CloudStore",
    "Verification",
    "downsample",
    "verify",
    "open3d_information_to_covariance",
    "fixed_covariance",
]

_CM = 0.01


class CompactCloud:
    """An (N,3) cloud in metres stored as int16 centimetres (|coordinate| < 327 m, 5 mm error)."""

    __slots__ = ("_cm",)

    def __init__(self, points: np.ndarray):
        p = np.asarray(points, dtype=np.float64)
        if len(p) and np.abs(p).max() >= 327.0:
            raise ValueError("CompactCloud holds coordinates below 327 m only")
        self._cm = np.round(p / _CM).astype(np.int16)

    def __len__(self) -> int:
        return len(self._cm)

    @property
    def nbytes(self) -> int:
        return self._cm.nbytes

    def points(self) -> np.ndarray:
        """(N,3) float64 metres."""
        return self._cm.astype(np.float64) * _CM


class CloudStore:
    """Append-only store of :class:`CompactCloud` s (int16 centimetres), numbered 0, 1, ...

    The clouds go to an unlinked temporary file (``tempfile.TemporaryFile`` in
    ``directory`` or the system's temporary folder; the OS deletes it when the store is
    closed or the process ends): written once, read back with ``pread`` only when a
    candidate is verified. In memory: 16 bytes a cloud (offset and length). ``spill=False``,
    or a failure to create or write the file (no space, read-only folder), keeps the
    clouds in memory instead (logged once).
    """

    def __init__(self, spill: bool = True, directory: str | None = None):
        self._offsets = array("q")
        self._lengths = array("q")
        self._memory: list[np.ndarray] = []
        self._file = None
        self._writable = False
        self._end = 0
        if spill:
            try:
                self._file = tempfile.TemporaryFile(prefix="flowslam-loop-clouds-", dir=directory)
                self._writable = True
            except OSError as error:
                log.warning("loop closure: cannot create a spill file (%s); clouds stay in memory", error)

    def __len__(self) -> int:
        return len(self._lengths)

    def append(self, cloud: CompactCloud) -> int:
        """Store ``cloud``; returns its number."""
        cm = np.ascontiguousarray(cloud._cm, dtype=np.int16)
        if self._writable:
            try:
                written = os.pwrite(self._file.fileno(), cm.tobytes(), self._end)
                if written != cm.nbytes:
                    raise OSError(f"short write ({written} of {cm.nbytes} bytes)")
            except OSError as error:
                log.warning("loop closure: spill file failed (%s); further clouds stay in memory", error)
                self._writable = False  # the clouds already there stay readable
            else:
                self._offsets.append(self._end)
                self._lengths.append(len(cm))
                self._end += cm.nbytes
                return len(self._lengths) - 1
        self._offsets.append(-1 - len(self._memory))
        self._lengths.append(len(cm))
        self._memory.append(cm)
        return len(self._lengths) - 1

    def points(self, number: int) -> np.ndarray:
        """(N,3) float64 metres of cloud ``number``."""
        offset, n = self._offsets[number], self._lengths[number]
        if offset < 0:
            cm = self._memory[-1 - offset]
        else:
            data = os.pread(self._file.fileno(), n * 6, offset)
            cm = np.frombuffer(data, dtype=np.int16).reshape(n, 3)
        return cm.astype(np.float64) * _CM

    @property
    def nbytes(self) -> int:
        """Bytes held in memory (index plus the clouds not spilled)."""
        return 16 * len(self._lengths) + sum(c.nbytes for c in self._memory)

    @property
    def disk_bytes(self) -> int:
        """Bytes in the spill file."""
        return self._end

    def _close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError:  # pragma: no cover
                pass
        self._file = None
        self._writable = False

    def __del__(self):
        self._close()


def downsample(points: np.ndarray, config: VerificationConfig, seed: int = 0) -> np.ndarray:
    """Voxel-downsample (N,3) points (m) within ``max_range_m`` to at most ``max_points``:
    Open3D's ``voxel_down_sample`` centroids (the same voxels and numbers, compiled, in
    voxel-key order: :func:`flowslam.compiled_voxels.open3d_voxel_means`), then a seeded
    random subset of them where there are more."""
    from flowslam.compiled_voxels import open3d_voxel_means

    p = np.asarray(points, dtype=np.float64)
    q, _ = open3d_voxel_means(p, config.voxel_m, np.einsum("ij,ij->i", p, p) < config.max_range_m**2)
    if len(q) > config.max_points:
        q = q[np.random.default_rng(seed).choice(len(q), config.max_points, replace=False)]
    return q


@dataclass
class Verification:
    """Outcome of :func:`verify` (see module doc for frames and units)."""

    accepted: bool
    T_target_source: np.ndarray
    fitness: float
    inlier_rmse: float
    covariance: np.ndarray
    reason: str = ""
    """Why it was rejected (empty when accepted)."""


def fixed_covariance(config: VerificationConfig) -> np.ndarray:
    """Diagonal 6x6 loop covariance [rot rad, trans m] from the configured sigmas."""
    return geometry.pose_covariance(np.deg2rad(config.rotation_sigma_deg), config.translation_sigma_m)


def open3d_information_to_covariance(
    information: np.ndarray, T_target_source: np.ndarray, point_sigma_m: float
) -> np.ndarray:
    """Covariance in GTSAM's right perturbation of ``T_target_source`` from Open3D's information.

    ``information`` is Open3D's unit-noise ``sum J^T J`` ([rot, trans], left
    perturbation in the target frame); ``point_sigma_m`` is the per-axis noise of a
    correspondence (m), so ``Sigma_l = point_sigma^2 * inv(information)``.
    """
    Ad_inv = np.linalg.inv(geometry.adjoint(T_target_source))
    cov_left = point_sigma_m**2 * np.linalg.inv(information)
    cov = Ad_inv @ cov_left @ Ad_inv.T
    return 0.5 * (cov + cov.T)


def _cloud(points: np.ndarray):
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))


def verify(
    source: np.ndarray,
    target: np.ndarray,
    T_init: np.ndarray,
    config: VerificationConfig | None = None,
) -> Verification:
    """Align ``source`` (N,3, frame j) to ``target`` (M,3, frame i) from ``T_init`` = guess of ``T_i_j``.

    Both clouds should already be downsampled (:func:`downsample`). Runs one ICP
    stage per ``correspondence_m`` (the first on clouds downsampled to twice
    ``voxel_m``), then scores the result at ``fitness_distance_m``.
    """
    import open3d as o3d

    c = config or VerificationConfig()
    reg = o3d.pipelines.registration
    src, tgt = _cloud(source), _cloud(target)
    radius = 3.0 * c.voxel_m
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=20))
    coarse_src, coarse_tgt = src.voxel_down_sample(2 * c.voxel_m), tgt.voxel_down_sample(2 * c.voxel_m)
    coarse_tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * radius, max_nn=20))
    T = np.asarray(T_init, dtype=np.float64).copy()
    criteria = reg.ICPConvergenceCriteria(max_iteration=c.max_iterations)
    for stage, max_dist in enumerate(c.correspondence_m):
        s, t = (coarse_src, coarse_tgt) if stage == 0 and len(c.correspondence_m) > 1 else (src, tgt)
        result = reg.registration_icp(
            s, t, max_dist, T, reg.TransformationEstimationPointToPlane(), criteria
        )
        T = np.asarray(result.transformation).copy()
    score = reg.evaluate_registration(src, tgt, c.fitness_distance_m, T)
    fitness, rmse = float(score.fitness), float(score.inlier_rmse)

    cov = fixed_covariance(c)
    if c.covariance == "icp" and fitness > 0:
        info = reg.get_information_matrix_from_point_clouds(src, tgt, c.fitness_distance_m, T)
        if np.linalg.matrix_rank(info) == 6:
            cov = cov + open3d_information_to_covariance(info, T, rmse / np.sqrt(3.0))

    reason = ""
    if fitness < c.min_fitness:
        reason = f"fitness {fitness:.3f} < {c.min_fitness}"
    elif rmse > c.max_rmse_m:
        reason = f"inlier RMSE {rmse:.3f} m > {c.max_rmse_m} m"
    return Verification(not reason, T, fitness, rmse, cov, reason)
