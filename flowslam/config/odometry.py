"""Options of the odometry front ends that are not learned: ``kiss_icp:`` and
``flow_odometry:`` (flow pairs -> relative pose, shared by every flow frontend).

Metres, seconds, radians, except fields whose name says ``_deg``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from flowslam.config.base import StrictModel

KernelName = Literal["huber", "cauchy", "geman_mcclure", "l2"]
"""Robust kernels of ``flowslam.registration.kernels`` (a test keeps the two lists equal)."""


class KissIcpConfig(StrictModel):
    """Options of the ``kiss-icp`` frontend (passed to the kiss-icp package)."""

    max_range: float = Field(100.0, gt=0)
    """Points farther than this from the sensor are dropped (m); above ``min_range``."""
    min_range: float = Field(0.0, ge=0)
    """Points nearer than this are dropped (m)."""
    deskew: bool = True
    """Correct the motion during the sweep (needs per-point times)."""
    voxel_size: float | None = Field(None, gt=0)
    """Map voxel size (m); None: max_range / 100, as kiss-icp does."""
    max_points_per_voxel: int = Field(20, ge=1)
    """Points kept per map voxel."""
    rotation_std_deg: float = Field(0.1, gt=0)
    """kiss-icp reports no covariance: the odometry measurement gets this fixed 1-sigma (deg)."""
    translation_std_m: float = Field(0.05, gt=0)
    """... and this fixed 1-sigma translation (m) per axis."""

    @model_validator(mode="after")
    def _range_interval(self):
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range ({self.min_range} m) must be below max_range ({self.max_range} m)")
        return self


class FlowOdometryConfig(StrictModel):
    """Options of ``FlowToPose``: robust registration of flow pairs into ``T_prev_curr``
    and its covariance, with a constant-velocity fallback."""

    kernel: KernelName = "cauchy"
    """Final IRLS kernel ('huber', 'cauchy', 'geman_mcclure', 'l2'); a Huber pass always runs first."""
    max_points: int = Field(30000, ge=0)
    """Pairs used for registration (seeded random subsample); 0 = all."""
    seed: int = 0
    """Seed of that subsample (and of RANSAC)."""
    min_static_points: int = Field(50, ge=3)
    """Fewer usable (finite, static) pairs than this -> constant-velocity fallback."""
    inlier_threshold_m: float = Field(0.1, gt=0)
    """Residual bound (m) for the inlier share, the RANSAC threshold and the MSAC comparison."""
    ransac_below_inlier_ratio: float = Field(0.5, ge=0, le=1)
    """Run RANSAC when the IRLS solution has a smaller inlier share than this."""
    min_inlier_ratio: float = Field(0.2, ge=0, le=1)
    """Final inlier share below this -> fallback (``few_inliers``)."""
    ransac_max_iterations: int = Field(1000, ge=1)
    """RANSAC hypotheses at most."""
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
