"""Frontend ``ransac``: FPFH features + Open3D RANSAC global registration of consecutive scans.

This is the baseline of the SSF-PAN paper: the default registration of its A-LOAM and
S-LOAM comparisons. It is kept **as published and intentionally untuned**: the options
(``ransac:`` section, :class:`flowslam.config.RansacConfig`) default to Open3D's global
registration tutorial relative to the voxel size, and the optional point-to-plane ICP
refinement (``icp_refine``) is off by default.

Per scan ``k``
--------------
Steps 1-3 are :class:`flowslam.registration.global_registration.FpfhRansac` (shared with
the motion-fault recovery of ``ssf``); this module adds the covariance and the fallbacks.

1. **Features** (once per scan): points beyond ``max_range_m`` dropped, voxel
   downsampling (``voxel_size_m``), normals (radius 2 x voxel), FPFH (radius 5 x voxel).
   The downsampled cloud and its features are kept as the next scan's target.
2. **RANSAC**: ``registration_ransac_based_on_feature_matching`` with scan ``k`` as the
   *source* and scan ``k-1`` as the *target* (mutual filter, ``ransac_n`` = 3 matches
   per hypothesis, edge-length and distance checkers, point-to-point estimation,
   distance 1.5 x voxel). Open3D's generator is seeded with ``seed`` before every call
   (``o3d.utility.random.seed``), but Open3D draws its hypotheses in parallel threads,
   so two identical calls can still pick a slightly different consensus (measured on
   KITTI 00: 2 of 30 repeated calls differed, fitness 0.962 vs 0.956; both poses
   within the accuracy below). The result is a *minimal*
   hypothesis (3 matches) chosen by the largest consensus, not a least-squares fit:
   on 64-beam scans at the default 0.5 m voxel it is accurate to about half a voxel
   (tens of cm), not to ICP's centimetres.
3. **ICP** (``icp_refine: true`` only): point-to-plane ICP of the two downsampled
   clouds from the RANSAC pose (distance 0.4 x voxel), as in the tutorial.

Frames and units
----------------
Registering source = scan k onto target = scan k-1 gives ``T_target_source`` =
``T_prev_curr`` directly (maps points of scan k into sensor frame k-1; 4x4, metres),
the measurement :mod:`flowslam.interfaces` asks for. No inversion is needed.

Covariance (how the graph can weigh it)
---------------------------------------
6x6 in GTSAM's Pose3 tangent of ``T_prev_curr``: ``[rot rad, trans m]``, right
perturbation ``T_prev_curr @ Exp(xi)``.

1. **Gauss-Newton covariance of the aligned pairs**: the pairs (point of scan k,
   nearest point of scan k-1 within the RANSAC distance) that Open3D's consensus
   counted for the chosen pose (with ``icp_refine``: ICP's final pairs) go to
   :func:`flowslam.registration.covariance.covariance_from_residuals` with
   ``src`` = scan k points, ``dst`` = scan k-1 points and ``T`` = ``T_prev_curr``:
   that function's ``T_dst_src`` *is* ``T_prev_curr``, so its right-perturbation
   tangent is already the measurement's (no :func:`inverse_covariance`). It gives
   ``sigma^2 (sum J^T J)^-1``: the directions the scene constrains, with the residual
   variance ``sigma^2`` estimated from the pairs (large for a coarse pose).
2. **Effective sample size**: multiplied by ``max(1, pairs / effective_samples)``. The
   RANSAC pose is fitted to ``ransac_n`` sampled matches, so the thousands of pairs
   count as ``effective_samples`` (default 3) independent points: the covariance keeps
   the shape of all pairs but the size of a 3-point fit with the pairs' residual
   noise. After ICP (a least-squares fit to all pairs, with correlated errors from the
   voxel grid) they count as ``icp_effective_samples`` (default 100), as ``FlowToPose``
   does for flow.
3. **Poor fit**: a RANSAC fitness below ``good_fitness`` multiplies it by
   ``(good_fitness / fitness)^2`` (little overlap: less trust).
4. **Floor**: ``diag(min_rotation_std^2 x3, min_translation_std^2 x3)`` is added.

Failure and fallback
--------------------
When a pair cannot be registered the measurement is the constant-velocity prediction
of :mod:`flowslam.motion_model` (options ``flow_odometry.fallback_*`` /
``no_prior_*``), with its inflated covariance, and ``stats`` say so exactly as
``FlowToPose`` does (``fallback``, ``fallback_code``, ``reason``), so ``run.json``
counts it (:func:`flowslam.fallbacks.summarize_fallbacks`):

- ``few_points``: fewer than ``min_points`` downsampled points in scan k or k-1;
- ``few_inliers``: RANSAC fitness below ``min_fitness`` or fewer than ``min_inliers``
  aligned pairs (e.g. scans without overlap, or a hypothesis that matched nothing);
- ``degenerate``: the covariance is singular (collinear pairs).

Known failure modes of the baseline (not repaired here, on purpose):

- the minimal-sample pose is coarse (above), and it is *biased short*: fitness counts
  every point of scan k with a scan k-1 neighbour within the RANSAC distance, and the
  ground's scan rings, which travel with the sensor, match best at zero motion, so the
  winning hypothesis tends to under-run the true step (measured: steps 75-90 % of the
  true length on KITTI and simulated scans, more with sparse 16-beam scans). The
  errors therefore add up along the path instead of averaging out;
- a wrong pose that keeps only the ground plane aligned still scores ~0.4 (a mirrored
  scan does), just under the default ``min_fitness``; a wrong pose scoring above it
  passes unflagged;
- repetitive structure (a straight road with regular facades) makes FPFH matches
  ambiguous along the road.

Stats per frame: ``fitness``, ``inlier_rmse_m`` (Open3D's, of the RANSAC pose),
``correspondences`` (RANSAC's aligned pairs), ``inliers`` (pairs behind the covariance:
the same, or ICP's), ``points`` / ``target_points`` (downsampled), ``icp_fitness`` /
``icp_rmse_m`` with ICP, and ``stage_ms`` (``features``, ``ransac``, ``icp``, ms).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from flowslam import geometry
from flowslam.config import FlowOdometryConfig, PipelineConfig, RansacConfig
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput
from flowslam.motion_model import ConstantVelocityPredictor
from flowslam.registration.covariance import covariance_from_residuals
from flowslam.registration.global_registration import FpfhRansac, ScanFeatures

__all__ = ["PairRegistration", "RansacFrontend", "ScanFeatures", "make_frontend"]


@dataclass
class PairRegistration:
    """Outcome of :meth:`RansacFrontend.register`: ``T_target_source`` (4x4; for scans k
    onto k-1 that is ``T_prev_curr``), its covariance (6x6, [rot rad, trans m], right
    perturbation; None on failure), ``stats`` and, on failure, the fallback ``code``
    (:data:`flowslam.fallbacks.FALLBACK_CODES`) and ``reason``."""

    T_target_source: np.ndarray
    covariance: np.ndarray | None
    stats: dict = field(default_factory=dict)
    code: str | None = None
    reason: str | None = None


def _millis(start: float) -> float:
    return (time.perf_counter() - start) * 1e3


class RansacFrontend:
    """FPFH + RANSAC registration of scan k onto scan k-1 (module doc); one per sequence."""

    name = "ransac"
    config_sections = ("ransac", "flow_odometry")
    """The config sections it reads (an option of another section given on the command line is an error)."""

    def __init__(self, options: RansacConfig | None = None, fallback: FlowOdometryConfig | None = None):
        """``fallback``: the constant-velocity model's options (``flow_odometry`` section)."""
        self.options = options or RansacConfig()
        self.predictor = ConstantVelocityPredictor(fallback or FlowOdometryConfig())
        self.global_registration = FpfhRansac(self.options)
        """Features and alignment (shared with the motion-fault recovery of ``ssf``)."""
        self._prev: ScanFeatures | None = None
        g = self.global_registration
        self.normal_radius_m, self.fpfh_radius_m = g.normal_radius_m, g.fpfh_radius_m
        self.distance_m, self.icp_distance_m = g.distance_m, g.icp_distance_m

    @property
    def fallbacks(self) -> Counter[str]:
        """Fallbacks so far, by code (see :data:`flowslam.fallbacks.FALLBACK_CODES`)."""
        return self.predictor.fallbacks

    def features(self, points: np.ndarray, timestamp: float = 0.0) -> ScanFeatures:
        """Crop, downsample, normals and FPFH of one scan ((N,3) points, sensor frame, m)."""
        return self.global_registration.features(points, timestamp)

    # -- registration ------------------------------------------------------------

    def register(self, source: ScanFeatures, target: ScanFeatures) -> PairRegistration:
        """RANSAC (and ICP) of ``source`` onto ``target`` with the covariance recipe of the
        module doc; ``code`` says why it failed (then ``T_target_source`` is not to be used)."""
        c = self.options
        stats: dict = {"points": len(source.points), "target_points": len(target.points), "stage_ms": {}}
        if source.features is None or target.features is None:
            return PairRegistration(np.eye(4), None, stats, "few_points", (
                f"fewer than {c.min_points} downsampled points (scan k: {len(source.points)}, "
                f"scan k-1: {len(target.points)})"))
        aligned = self.global_registration.align(source, target)
        stats.update(aligned.stats, stage_ms=aligned.laps)
        T, pairs, fitness = aligned.T_target_source, aligned.pairs, aligned.stats["fitness"]
        n_eff = c.icp_effective_samples if aligned.refined else c.effective_samples
        if fitness < c.min_fitness or len(pairs) < c.min_inliers:
            return PairRegistration(T, None, stats, "few_inliers", (
                f"RANSAC fitness {fitness:.3f} (min {c.min_fitness}), {len(pairs)} aligned pairs "
                f"(min {c.min_inliers})"))
        try:
            cov = covariance_from_residuals(source.points[pairs[:, 0]], target.points[pairs[:, 1]], T)
        except ValueError as e:
            return PairRegistration(T, None, stats, "degenerate", f"registration covariance: {e}")
        cov = cov * max(1.0, len(pairs) / n_eff)
        if fitness < c.good_fitness:
            cov = cov * (c.good_fitness / fitness) ** 2
        cov = cov + geometry.pose_covariance(np.deg2rad(c.min_rotation_std_deg), c.min_translation_std_m)
        return PairRegistration(T, cov, stats)

    # -- the frontend ------------------------------------------------------------

    def process(self, frame: Frame) -> FrontendOutput:
        start = time.perf_counter()
        scan = self.features(frame.points, float(frame.timestamp))
        features_ms = _millis(start)
        prev, self._prev = self._prev, scan
        if prev is None:
            stats = {"points": len(scan.points), "stage_ms": {"features": features_ms}}
            return FrontendOutput(index=frame.index, T_prev_curr=None, stats=dict(stats, fallback=False, reason=None))
        dt = scan.timestamp - prev.timestamp
        dt = dt if dt > 0 else None
        r = self.register(scan, prev)
        stats = r.stats
        stats["stage_ms"] = {"features": features_ms, **stats["stage_ms"]}
        if r.code is None:
            T, cov = r.T_target_source, r.covariance
            self.predictor.update(T, cov, dt)
            stats.update(fallback=False, reason=None, method="ransac+icp" if self.options.icp_refine else "ransac")
        else:
            T, cov, marks = self.predictor.fall_back(r.code, r.reason, dt)
            stats.update(marks)
        stats["time_ms"] = _millis(start)
        return FrontendOutput(index=frame.index, T_prev_curr=T, covariance=cov, stats=stats)


def make_frontend(config: PipelineConfig) -> RansacFrontend:
    """Factory of ``ransac`` (options ``config.ransac``; fallback model ``config.flow_odometry``)."""
    return RansacFrontend(config.ransac, config.flow_odometry)
