"""Options of loop closure (``loop_closure:`` in the run config): Scan Context place
recognition and ICP verification.

The ``s-loam`` variant is ``loop_closure.enabled: true`` (the default); ``a-loam`` is
``false``. A loop closer is built only for backends that take loops (``isam2``).
Units: metres and radians, except fields whose name says ``_deg``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from flowslam.config.base import StrictModel


class ScanContextConfig(StrictModel):
    """The Scan Context descriptor (Kim & Kim, IROS 2018): rings x sectors of max height."""

    rings: int = Field(20, ge=2)
    """Radial bins of equal width over ``(0, max_range_m]``."""
    sectors: int = Field(60, ge=4)
    """Azimuthal bins of equal width over 360 deg (60 = 6 deg, the yaw resolution)."""
    max_range_m: float = Field(80.0, gt=0)
    """Points farther than this (horizontal distance) are ignored."""
    height_offset_m: float = 2.0
    """Added to z (sensor frame) before taking the max, so ground bins are > 0 and empty ones 0."""


class VerificationConfig(StrictModel):
    """Geometric verification of a candidate pair with Open3D point-to-plane ICP."""

    voxel_m: float = Field(0.75, gt=0)
    """Voxel size of the clouds kept for verification (also the fine ICP resolution)."""
    max_range_m: float = Field(80.0, gt=0, le=300)
    """Points farther than this are not kept (3D range, m; kept clouds are int16 cm)."""
    max_points: int = Field(12000, ge=100)
    """Cap on the kept points per scan (random subset beyond it)."""
    correspondence_m: tuple[float, ...] = (5.0, 2.0, 1.0)
    """Coarse-to-fine ICP max correspondence distances; the first stage runs on 2x voxels."""
    max_iterations: int = Field(30, ge=1)
    """ICP iterations per stage."""
    fitness_distance_m: float = Field(1.0, gt=0)
    """Neighbour distance for the final fitness (overlap) and inlier RMSE."""
    min_fitness: float = Field(0.5, ge=0, le=1)
    """Accept only if at least this share of the current scan's points has a neighbour."""
    max_rmse_m: float = Field(0.5, gt=0)
    """... and the inlier RMSE is at most this."""
    covariance: Literal["fixed", "icp"] = "fixed"
    """Loop covariance: the fixed sigmas below, or ICP's point-to-point information scaled by
    the inlier RMSE (Open3D, converted to GTSAM's right perturbation) plus the fixed one."""
    rotation_sigma_deg: float = Field(1.0, gt=0)
    """Fixed loop covariance: rotation 1-sigma per axis (deg) ..."""
    translation_sigma_m: float = Field(0.1, gt=0)
    """... and translation 1-sigma per axis (m)."""


class LoopClosureConfig(StrictModel):
    """Candidate search (ring-key KD-tree), exclusions, descriptor threshold, verification."""

    enabled: bool = True
    """Detect loops and add them to the graph (variant ``s-loam``); False = ``a-loam``."""
    scan_context: ScanContextConfig = ScanContextConfig()
    """The place descriptor."""
    verification: VerificationConfig = VerificationConfig()
    """ICP check of a candidate pair."""
    num_candidates: int = Field(10, ge=1)
    """Nearest ring keys looked at; the best by column-shift distance is verified."""
    tree_rebuild_every: int = Field(50, ge=1)
    """Rebuild the ring-key KD-tree once this many new scans became eligible."""
    exclude_recent_frames: int = Field(100, ge=1)
    """Never match a scan with one of the previous N scans ..."""
    exclude_recent_m: float = Field(30.0, ge=0)
    """... nor with scans less than this far back along the travelled path (m)."""
    distance_threshold: float = Field(0.2, gt=0, le=1)
    """Scan Context distance (cosine, 0..1) below which the best candidate is verified."""
    gate_base_m: float = Field(5.0, ge=0)
    """Spatial gate: a candidate is considered only if its current position estimate lies
    within ``gate_base_m + gate_drift_fraction * (path travelled between the two scans)`` of
    the current scan's, and the accepted loop may correct the estimate by no more than
    that. True loops pass for odometry that drifts less than the fraction; look-alike
    places far away (repetitive streets, a procedural town) do not."""
    gate_drift_fraction: float = Field(0.03, ge=0)
    """The drift share of that gate (see ``gate_base_m``)."""
    cooldown_frames: int = Field(5, ge=0)
    """After an accepted loop, skip detection for this many scans."""
