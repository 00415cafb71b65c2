"""Flow to pose: the odometry measurement of every flow-based frontend.

Frames
------
Scene flow follows Argoverse 2: for a point ``p_i`` of scan ``k-1`` (sensor frame
``k-1``), ``p_i + f_i`` is the same physical point at scan ``k`` in sensor frame
``k``. For the static points therefore ``p_i + f_i = T_{k,k-1} p_i``, so the pairs

    src_i = p_i            (frame k-1)        dst_i = p_i + f_i      (frame k)

registered robustly give ``T_dst_src = T_{k,k-1} = T_curr_prev``. The odometry
measurement handed to the backend is its inverse ``T_prev_curr = inv(T_curr_prev)``
(maps scan ``k`` into frame ``k-1``), see :mod:`flowslam.interfaces`.

Covariance of the inverse
-------------------------
The registration reports ``Sigma`` in the right-perturbation tangent of
``T = T_curr_prev``: ``T_true = T Exp(xi)``, ``xi ~ N(0, Sigma)``, ``xi = [omega, v]``.
Then, exactly (``T Exp(xi) T^-1 = Exp(Ad_T xi)``)::

    T_true^-1 = Exp(-xi) T^-1 = T^-1 (T Exp(-xi) T^-1) = T^-1 Exp(-Ad_T xi)

so the perturbation of the inverse is ``eta = -Ad_T xi`` and
``Cov(eta) = Ad_T Sigma Ad_T^T``, with GTSAM's adjoint in ``[rot, trans]`` order
``Ad_T = [[R, 0], [hat(t) R, R]]`` (``R, t`` of ``T_curr_prev``;
``gtsam.Pose3.AdjointMap``). Checked against GTSAM in ``tests/test_flow_odometry.py``.

Realistic covariance (the choice made here)
-------------------------------------------
The registration core's covariance ``sigma^2 (sum J^T J)^-1`` assumes independent
per-point noise, so it shrinks as ``1/N``: with 30k points and ``sigma`` = 1e-4 m it
claims micrometres. Flow errors are not independent (a network errs by region and by
object; labels are rounded jointly), so two corrections are applied, in this order:

1. **Effective sample size**: the covariance is multiplied by
   ``max(1, n_inliers / effective_samples)``, i.e. the data count as at most
   ``effective_samples`` (default 100) independent points. The *shape* of the
   information (which directions the scene constrains) is kept; only its amount is
   capped. With ``sigma`` = 3 cm and a 20 m scene this gives ~3 mm and ~0.005 deg.
2. **Floor**: ``diag(min_rotation_std^2 x3, min_translation_std^2 x3)`` (defaults
   0.01 deg and 5 mm) is *added* in the tangent of ``T_prev_curr`` (model errors the
   residuals cannot show: timing, deskew, calibration). Exact GT flow thus gets
   exactly this covariance, which keeps the backend well conditioned.

Degeneracy and fallback
-----------------------
The estimate falls back to the **constant-velocity prediction** (the last registered
``T_prev_curr``, its twist scaled by the ratio of scan intervals when both are known)
with an inflated covariance when

- fewer than ``min_static_points`` usable (finite, static, non-zero weight) pairs
  remain (code ``few_points``);
- the normal equations are ill-conditioned (code ``ill_conditioned``): the condition
  number of the scaled 6x6 information exceeds its threshold. Two informations are
  checked, both about the centroid of the used points with rotations scaled by ``L``
  = the RMS distance of the points from that centroid (so a rotation ``omega`` counts as
  the displacement ``L omega`` it causes, and both blocks are in metres):

  * *correspondence*: the point-to-point information of the flow pairs (singular only
    for (nearly) collinear points; threshold ``max_condition_correspondence``);
  * *geometry*: the point-to-plane information ``sum a a^T``, ``a = [(c x n)/L, n]``,
    of planar surfels (``geometry_voxel_size`` voxels, default 2 m, normal ``n`` by PCA,
    weight = planarity, one vote per voxel; on at most 10000 of the used points). This
    is what the scene's geometry can tell a flow estimator: in a corridor no surface
    faces along the corridor, so the along-axis motion is unobservable to any
    geometry-based flow (aperture problem) even though the flow pairs themselves look
    well conditioned. Real scans score 7-20 (AV2, KITTI; 3k to 30k points), a
    two-wall corridor with floor > 600; threshold ``max_condition`` (default 100).
    Scenes with fewer than 6 planar surfels count as degenerate (unstructured random
    points: switch the check off with ``check_geometry: false``).
- the registration fails (``degenerate``) or keeps too few inliers (``few_inliers``).

The fallback covariance is ``fallback_inflation * C_last + m * diag(fallback_std^2)``
with ``C_last`` the covariance of the last registered measurement and ``m`` the number
of consecutive fallbacks (a random walk on the velocity). Without any previous
measurement the prediction is the identity (standing still) with
``diag(no_prior_std^2)``. Fallbacks are counted by code (:attr:`FlowToPose.fallbacks`,
:func:`summarize_fallbacks` for the run report).

Speed
-----
At most ``max_points`` (default 30000) usable pairs, drawn at random with a fixed seed
(deterministic per input), go to the registration and the conditioning checks; the
final inlier mask is evaluated on all points. About 15 ms for a 100k-point scan.

Registration
------------
IRLS with a Huber kernel from the least-squares start (convex; stopped at 1e-5 rad/m
steps), then IRLS with ``kernel`` (default Cauchy, redescending: a moving object's pull
vanishes) from there, to 1e-7 rad/m steps.
If fewer than ``ransac_below_inlier_ratio`` of the used pairs lie within
``inlier_threshold_m`` of that solution, RANSAC (threshold ``inlier_threshold_m``, then
IRLS refinement) runs too and the solution with the lower MSAC cost is kept.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from flowslam import geometry
from flowslam.mapping import voxel_ids
from flowslam.registration import RegistrationResult, irls, ransac
from flowslam.registration.closed_form import squared_residuals
from flowslam.registration.kernels import get_kernel, kernel_names
from flowslam.registration.robust import INLIER_FACTOR

log = logging.getLogger(__name__)

__all__ = [
    "FlowOdometryConfig",
    "FlowPoseEstimate",
    "FlowToPose",
    "ConstantVelocityPredictor",
    "inverse_covariance",
    "correspondence_condition",
    "geometry_condition",
    "summarize_fallbacks",
    "FALLBACK_CODES",
]

#: Fallback codes and what they mean (keys of :attr:`FlowToPose.fallbacks`).
FALLBACK_CODES = {
    "few_points": "fewer usable static points than min_static_points",
    "ill_conditioned": "condition number of the scaled information above the threshold",
    "degenerate": "registration failed (collinear points, singular covariance)",
    "few_inliers": "too few pairs agree with the registered motion",
    "no_flow": "the frame has no flow (frontend-reported)",
}


class FlowOdometryConfig(BaseModel):
    """Options of :class:`FlowToPose` (YAML section ``flow_odometry``). Metres, seconds,
    radians except ``_deg`` fields."""

    model_config = ConfigDict(extra="forbid")

    kernel: str = "cauchy"
    """Final IRLS kernel ('huber', 'cauchy', 'geman_mcclure', 'l2'); a Huber pass always runs first."""
    max_points: int = Field(30000, ge=0)
    """Pairs used for registration (seeded random subsample); 0 = all."""
    seed: int = 0
    min_static_points: int = Field(50, ge=3)
    """Fewer usable (finite, static) pairs than this -> constant-velocity fallback."""
    inlier_threshold_m: float = Field(0.1, gt=0)
    """Residual bound (m) for the inlier share, the RANSAC threshold and the MSAC comparison."""
    ransac_below_inlier_ratio: float = Field(0.5, ge=0, le=1)
    """Run RANSAC when the IRLS solution has a smaller inlier share than this."""
    min_inlier_ratio: float = Field(0.2, ge=0, le=1)
    """Final inlier share below this -> fallback (``few_inliers``)."""
    ransac_max_iterations: int = Field(1000, ge=1)
    check_geometry: bool = True
    """Run the point-to-plane (corridor) degeneracy check."""
    max_condition: float = Field(100.0, gt=1)
    """Geometry (point-to-plane surfel) condition number above which the scan is degenerate."""
    max_condition_correspondence: float = Field(1e4, gt=1)
    """Point-to-point condition number above which the pairs are degenerate (near-collinear)."""
    geometry_voxel_size: float = Field(2.0, gt=0)
    """Voxel (m) of the surfels of the geometry check."""
    effective_samples: float = Field(100.0, gt=0)
    """Covariance x max(1, n_inliers / effective_samples): flow errors are correlated."""
    min_rotation_std_deg: float = Field(0.01, ge=0)
    """Added covariance floor, rotation 1-sigma per axis (deg)."""
    min_translation_std_m: float = Field(0.005, ge=0)
    """Added covariance floor, translation 1-sigma per axis (m)."""
    fallback_inflation: float = Field(10.0, ge=1)
    """Variance multiplier of the last measurement covariance for a constant-velocity step."""
    fallback_rotation_std_deg: float = Field(0.5, ge=0)
    """Constant-velocity model error per fallback step, rotation 1-sigma (deg)."""
    fallback_translation_std_m: float = Field(0.2, ge=0)
    """Constant-velocity model error per fallback step, translation 1-sigma (m)."""
    no_prior_rotation_std_deg: float = Field(10.0, gt=0)
    """Fallback with no earlier measurement (identity motion): rotation 1-sigma (deg)."""
    no_prior_translation_std_m: float = Field(2.0, gt=0)
    """... and translation 1-sigma (m)."""

    @field_validator("kernel")
    @classmethod
    def _known_kernel(cls, v: str) -> str:
        try:
            get_kernel(v)
        except (ValueError, KeyError):
            raise ValueError(f"unknown kernel {v!r}; choose one of {kernel_names()}") from None
        return v


@dataclass
class FlowPoseEstimate:
    """The odometry measurement of one scan pair (frames: see module doc).

    ``T_prev_curr`` (4x4) maps scan k into frame k-1; ``covariance`` (6x6) is in its
    right-perturbation tangent ``[omega rad, v m]``; ``T_curr_prev`` = T_{k,k-1} =
    ``inv(T_prev_curr)``; ``inliers`` (N,) bool over the input points (pairs agreeing
    with the motion; all False on fallback); ``reason`` says why it fell back.
    """

    T_prev_curr: np.ndarray
    covariance: np.ndarray
    T_curr_prev: np.ndarray
    inliers: np.ndarray
    fallback: bool
    reason: str | None
    stats: dict = field(default_factory=dict)


def inverse_covariance(T: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance of ``inv(T)`` from the covariance of ``T`` (both right-perturbation,
    ``[rot, trans]``): ``Ad_T Sigma Ad_T^T`` (derivation in the module doc)."""
    A = geometry.adjoint(T)
    C = A @ covariance @ A.T
    return 0.5 * (C + C.T)


#: IRLS stops when an update moves less than this (rad and m): far below any flow noise.
_TOLERANCE = 1e-7
#: The Huber pass only initialises the redescending one.
_HUBER_TOLERANCE = 1e-5
#: The geometry check uses at most this many of the registered points (a strided subset).
GEOMETRY_SAMPLES = 10000


def _scaled_condition(H: np.ndarray) -> float:
    """Condition number of a symmetric PSD 6x6 matrix (inf when singular)."""
    e = np.linalg.eigvalsh(H)
    if not np.all(np.isfinite(e)) or e[-1] <= 0:
        return float("inf")
    return float(e[-1] / e[0]) if e[0] > 1e-15 * e[-1] else float("inf")


def correspondence_condition(src: np.ndarray) -> float:
    """Condition number of the point-to-point information of pairs with sources ``src``
    (N,3), about their centroid, rotation scaled by the RMS radius ``L`` (module doc).

    Per point the (centred) information is ``[[|p|^2 I - p p^T, .], [., I]] / L^2``;
    about the centroid the cross block vanishes.
    """
    c = np.ascontiguousarray(src.T)  # (3,N): einsum over contiguous rows, no BLAS
    c -= c.mean(axis=1, keepdims=True)
    S2 = np.einsum("in,jn->ij", c, c) / c.shape[1]
    L2 = float(np.trace(S2))
    if not L2 > 0:
        return float("inf")
    H = np.zeros((6, 6))
    H[:3, :3] = (L2 * np.eye(3) - S2) / L2
    H[3:, 3:] = np.eye(3)
    return _scaled_condition(H)


def geometry_condition(points: np.ndarray, voxel_size: float = 2.0, min_voxel_points: int = 5) -> float:
    """Condition number of the point-to-plane information of the scene's surfels.

    Points (N,3, m) are grouped in ``voxel_size`` voxels; each voxel with at least
    ``min_voxel_points`` points gives a surfel: centroid ``m`` (relative to the
    points' centroid), normal ``n`` (smallest principal axis), planarity
    ``(l2 - l3) / l1`` (eigenvalues descending; 0 for lines and scatter, 1 for a
    plane). ``H = sum_v planarity_v a_v a_v^T / sum planarity``, ``a = [(m x n)/L, n]``,
    ``L`` the RMS radius of the points. ``inf`` if fewer than 6 surfels.
    """
    c0 = points.mean(axis=0)
    pc = points - c0
    L = float(np.sqrt(np.einsum("ni,ni->", pc, pc) / len(pc)))
    if not L > 0:
        return float("inf")
    inverse, counts = voxel_ids(pc, voxel_size)
    V = len(counts)
    S1 = np.stack([np.bincount(inverse, pc[:, i], V) for i in range(3)], axis=1)
    S2 = np.empty((V, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            S2[:, i, j] = S2[:, j, i] = np.bincount(inverse, pc[:, i] * pc[:, j], V)
    ok = counts >= min_voxel_points
    if np.count_nonzero(ok) < 6:
        return float("inf")
    n_v = counts[ok].astype(np.float64)
    m = S1[ok] / n_v[:, None]
    C = S2[ok] / n_v[:, None, None] - np.einsum("vi,vj->vij", m, m)
    w, vec = np.linalg.eigh(C)  # ascending
    normal = vec[:, :, 0]
    planarity = (w[:, 1] - w[:, 0]) / np.maximum(w[:, 2], 1e-12)
    wsum = float(planarity.sum())
    if not wsum > 0:
        return float("inf")
    a = np.hstack([np.cross(m, normal) / L, normal])
    H = np.einsum("v,vi,vj->ij", planarity, a, a) / wsum
    return _scaled_condition(H)


class ConstantVelocityPredictor:
    """Holds the last registered measurement and predicts the next one from it.

    ``predict(dt)`` returns ``T_prev_curr`` of the last registration, its twist scaled
    by ``dt / dt_last`` when both intervals are known (constant velocity in time, not
    per scan), and the covariance of a prediction ``misses`` steps after it (module doc).
    """

    def __init__(self, config: FlowOdometryConfig):
        self.config = config
        self.T_prev_curr: np.ndarray | None = None
        self.covariance: np.ndarray | None = None
        self.dt: float | None = None
        self.misses = 0
        """Consecutive predictions since the last registered measurement."""

    def update(self, T_prev_curr: np.ndarray, covariance: np.ndarray, dt: float | None) -> None:
        """Record a registered (non-fallback) measurement."""
        self.T_prev_curr = np.array(T_prev_curr, dtype=np.float64)
        self.covariance = np.array(covariance, dtype=np.float64)
        self.dt = dt if dt is not None and dt > 0 else None
        self.misses = 0

    def predict(self, dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(T_prev_curr, covariance) of the next scan pair; counts one more miss."""
        cfg = self.config
        self.misses += 1
        if self.T_prev_curr is None:
            rot, trans = np.deg2rad(cfg.no_prior_rotation_std_deg), cfg.no_prior_translation_std_m
            return np.eye(4), np.diag([rot**2] * 3 + [trans**2] * 3)
        T = self.T_prev_curr
        if dt is not None and dt > 0 and self.dt is not None:
            T = geometry.exp_se3(geometry.log_se3(T) * (dt / self.dt))
        rot, trans = np.deg2rad(cfg.fallback_rotation_std_deg), cfg.fallback_translation_std_m
        cov = cfg.fallback_inflation * self.covariance + self.misses * np.diag([rot**2] * 3 + [trans**2] * 3)
        return T.copy(), cov


def _msac_cost(residuals: np.ndarray, threshold: float) -> float:
    return float(np.minimum(residuals * residuals, threshold * threshold).sum())


class FlowToPose:
    """Odometry from scene flow: robust registration of ``(p_i, p_i + f_i)`` (module doc).

    One instance per sequence: it keeps the constant-velocity predictor and the
    fallback counts.
    """

    def __init__(self, config: FlowOdometryConfig | None = None):
        self.config = config or FlowOdometryConfig()
        self.predictor = ConstantVelocityPredictor(self.config)
        self.fallbacks: Counter[str] = Counter()
        """Fallbacks so far, by code (see ``FALLBACK_CODES``)."""
        self.estimates = 0
        """Calls to :meth:`estimate` / :meth:`fallback` so far."""

    # -- public -----------------------------------------------------------------

    def estimate(
        self,
        points: np.ndarray,
        flow: np.ndarray,
        static_mask: np.ndarray | None = None,
        weights: np.ndarray | None = None,
        dt: float | None = None,
    ) -> FlowPoseEstimate:
        """Motion between scan k-1 and scan k from the flow of scan k-1's points.

        Parameters
        ----------
        points:
            (N,3) points of scan k-1 in sensor frame k-1 (m).
        flow:
            (N,3) scene flow, Argoverse 2 convention (``points + flow`` in frame k).
            Rows with non-finite values are ignored.
        static_mask:
            Optional (N,) bool: only these points are registered (``None``: all, the
            robust registration then rejects moving ones).
        weights:
            Optional (N,) non-negative prior weights (e.g. flow confidences); zero
            excludes a point.
        dt:
            Optional time between the scans (s), used only to scale the
            constant-velocity prediction.
        """
        start = time.perf_counter()
        cfg = self.config
        points = np.asarray(points, dtype=np.float64)
        flow = np.asarray(flow, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or flow.shape != points.shape:
            raise ValueError(f"points and flow must both be (N,3); got {points.shape} and {flow.shape}")
        n = len(points)
        if np.isfinite(points).all() and np.isfinite(flow).all():  # fast path: no per-row pass
            usable = np.ones(n, dtype=bool)
        else:
            usable = np.isfinite(points).all(axis=1) & np.isfinite(flow).all(axis=1)
        if static_mask is not None:
            static_mask = np.asarray(static_mask, dtype=bool).reshape(-1)
            if static_mask.shape[0] != n:
                raise ValueError(f"static_mask must be (N,) with N={n}; got {static_mask.shape}")
            usable &= static_mask
        w_all = None
        if weights is not None:
            w_all = np.asarray(weights, dtype=np.float64).reshape(-1)
            if w_all.shape[0] != n:
                raise ValueError(f"weights must be (N,) with N={n}; got {w_all.shape}")
            usable &= np.isfinite(w_all) & (w_all > 0)
        idx = np.flatnonzero(usable)
        n_usable = int(idx.size)
        stats: dict = {"n_points": n, "n_static": n_usable}
        self.estimates += 1

        if n_usable < cfg.min_static_points:
            return self._fall_back(
                "few_points", f"only {n_usable} usable static points with flow (need {cfg.min_static_points})",
                n, dt, stats, start,
            )
        if cfg.max_points and n_usable > cfg.max_points:
            rng = np.random.default_rng(cfg.seed)
            idx = np.sort(rng.choice(idx, size=cfg.max_points, replace=False))
        # np.take, not fancy indexing: ~10x faster on (N,3) rows.
        src = np.take(points, idx, axis=0)
        dst = src + np.take(flow, idx, axis=0)
        w = None if w_all is None else w_all[idx]
        stats["n_used"] = int(idx.size)

        cond_c = correspondence_condition(src)
        stats["condition_correspondence"] = cond_c
        if not cond_c <= cfg.max_condition_correspondence:
            return self._fall_back(
                "ill_conditioned",
                f"ill-conditioned flow pairs (point-to-point condition {cond_c:.3g} > "
                f"{cfg.max_condition_correspondence:.3g}: nearly collinear points)",
                n, dt, stats, start,
            )
        if cfg.check_geometry:
            stride = -(-len(src) // GEOMETRY_SAMPLES)
            cond_g = geometry_condition(src[::stride], cfg.geometry_voxel_size)
            stats["condition_geometry"] = cond_g
            if not cond_g <= cfg.max_condition:
                return self._fall_back(
                    "ill_conditioned",
                    f"ill-conditioned geometry (point-to-plane condition {cond_g:.3g} > {cfg.max_condition:.3g}: "
                    "a direction no surface constrains, e.g. a corridor)",
                    n, dt, stats, start,
                )

        try:
            res, method = self._register(src, dst, w)
        except ValueError as e:
            return self._fall_back("degenerate", f"registration failed: {e}", n, dt, stats, start)
        share = float(np.count_nonzero(res.residuals < cfg.inlier_threshold_m)) / len(src)
        stats.update(
            method=method, iterations=int(res.iterations), scale_m=float(res.scale),
            rmse_m=float(res.rmse), inlier_share=share,
        )
        if share < cfg.min_inlier_ratio or res.num_inliers < cfg.min_static_points:
            return self._fall_back(
                "few_inliers",
                f"only {share:.0%} of the pairs within {cfg.inlier_threshold_m} m of the motion "
                f"({res.num_inliers} inliers)",
                n, dt, stats, start,
            )
        if not np.all(np.isfinite(res.covariance)):
            return self._fall_back("degenerate", "singular registration covariance", n, dt, stats, start)

        T_curr_prev = res.T
        T_prev_curr = geometry.inv(T_curr_prev)
        cov = res.covariance * max(1.0, res.num_inliers / cfg.effective_samples)
        cov = inverse_covariance(T_curr_prev, cov) + self._floor()

        # Inliers over all input points, at the registration's own bound (non-usable: never).
        bound = cfg.inlier_threshold_m if method == "ransac" else INLIER_FACTOR * float(res.scale)
        with np.errstate(invalid="ignore"):
            inliers = squared_residuals(points, points + flow, T_curr_prev) < bound * bound
        inliers &= usable
        n_inliers = int(np.count_nonzero(inliers))

        self.predictor.update(T_prev_curr, cov, dt)
        stats.update(
            fallback=False, reason=None, inliers=n_inliers,
            inlier_ratio=n_inliers / n_usable, inlier_bound_m=bound,
            time_ms=(time.perf_counter() - start) * 1e3,
        )
        return FlowPoseEstimate(T_prev_curr, cov, T_curr_prev, inliers, False, None, stats)

    def fallback(self, code: str, reason: str, n_points: int = 0, dt: float | None = None) -> FlowPoseEstimate:
        """The constant-velocity estimate for a pair the caller cannot register (e.g. a
        frame without flow); counted like any other fallback under ``code``."""
        self.estimates += 1
        return self._fall_back(code, reason, n_points, dt, {"n_points": n_points}, time.perf_counter())

    @property
    def fallback_count(self) -> int:
        return int(sum(self.fallbacks.values()))

    def reset(self) -> None:
        """Forget the predictor state and the counts (new sequence)."""
        self.predictor = ConstantVelocityPredictor(self.config)
        self.fallbacks.clear()
        self.estimates = 0

    # -- internals --------------------------------------------------------------

    def _floor(self) -> np.ndarray:
        rot = np.deg2rad(self.config.min_rotation_std_deg)
        trans = self.config.min_translation_std_m
        return np.diag([rot**2] * 3 + [trans**2] * 3)

    def _register(
        self, src: np.ndarray, dst: np.ndarray, w: np.ndarray | None
    ) -> tuple[RegistrationResult, str]:
        cfg = self.config
        res = irls(src, dst, kernel="huber", weights=w, max_iterations=30, tolerance=_HUBER_TOLERANCE)
        if get_kernel(cfg.kernel).name != "huber":
            res = irls(src, dst, kernel=cfg.kernel, init=res.T, weights=w, tolerance=_TOLERANCE)
        thr = cfg.inlier_threshold_m
        share = float(np.count_nonzero(res.residuals < thr)) / len(src)
        if share >= cfg.ransac_below_inlier_ratio:
            return res, "irls"
        try:
            rr = ransac(
                src, dst, threshold=thr, refine_kernel=cfg.kernel, seed=cfg.seed, weights=w,
                max_iterations=cfg.ransac_max_iterations, refine_tolerance=_TOLERANCE,
            )
        except ValueError as e:
            log.debug("RANSAC failed (%s); keeping the IRLS solution", e)
            return res, "irls"
        if _msac_cost(rr.residuals, thr) < _msac_cost(res.residuals, thr):
            return rr, "ransac"
        return res, "irls"

    def _fall_back(
        self, code: str, reason: str, n: int, dt: float | None, stats: dict, start: float
    ) -> FlowPoseEstimate:
        T_prev_curr, cov = self.predictor.predict(dt)
        self.fallbacks[code] += 1
        log.info("flow odometry fallback to constant velocity: %s", reason)
        stats.update(
            fallback=True, reason=reason, fallback_code=code, method="constant-velocity",
            inliers=0, inlier_ratio=0.0, consecutive_fallbacks=self.predictor.misses,
            time_ms=(time.perf_counter() - start) * 1e3,
        )
        return FlowPoseEstimate(
            T_prev_curr, cov, geometry.inv(T_prev_curr), np.zeros(n, dtype=bool), True, reason, stats
        )


def summarize_fallbacks(frontend_stats: list[dict]) -> dict:
    """Fallback counts for the run report from the per-frame ``FrontendOutput.stats``:
    ``{"frames": n, "fallbacks": k, "by_reason": {code: count}}``."""
    codes = Counter(s.get("fallback_code", "unknown") for s in frontend_stats if s.get("fallback"))
    return {"frames": len(frontend_stats), "fallbacks": int(sum(codes.values())), "by_reason": dict(codes)}
