"""Options of the scan-to-map stage (``mapping:`` in the run config), LOAM's mapping step.

Each scan's static points are registered to a local map of the recent static points,
and the result goes into the factor graph beside the flow odometry (backends with
factors only: ``isam2``, both variants). Units: metres and radians, except fields
whose name says ``_deg``.
"""

from __future__ import annotations

from pydantic import Field, model_validator

from flowslam.config.base import StrictModel


class MappingConfig(StrictModel):
    """Local map (the recent registered scans with normals) and the registration to it."""

    enabled: bool = True
    """Register scans to the local map and add the factors (graph backends only; on by
    default since it pays: simulated dt 300 frames, ssf a-loam drift 0.110 -> 0.022 %,
    APE 0.059 -> 0.013 m; docs/mapping.md)."""
    every: int = Field(1, ge=1)
    """Register every n-th scan only (the others get no map factor and are not mapped)."""
    insert_every: int = Field(3, ge=1)
    """Put every n-th registered scan in the map (the others are registered to it but
    not added; restarts and warm-up scans always go in). ``max_scans`` counts the scans
    in the map, so it spans up to ``insert_every * max_scans`` scans. 3 instead of 1:
    the stage's median 30 -> 14 ms per scan (with ``source_stride`` 2), drift equal or
    lower (docs/mapping.md)."""
    source_stride: int = Field(2, ge=1)
    """A scan that is registered but not put in the map uses every n-th of its points
    (its source cloud, ``source_voxel_m``, needs no more)."""
    map_voxel_m: float = Field(0.75, gt=0)
    """Voxel of the scans put in the map (normals from 10 neighbours in the scan)."""
    source_voxel_m: float = Field(1.0, gt=0)
    """Voxel of the points registered to the map."""
    max_distance_m: float = Field(40.0, gt=0)
    """Scans whose sensor is farther than this from the newest one leave the map (the
    'last N metres') ..."""
    max_scans: int = Field(30, ge=1)
    """... and the map holds at most this many scans (30: kitti00-path ssf a-loam drift
    0.112 -> 0.068 %, simulated dt 0.034 -> 0.023 %, against 20; docs/mapping.md)."""
    max_range_m: float = Field(80.0, gt=0)
    """Scan points farther than this from the sensor are not registered nor mapped."""
    min_range_m: float = Field(3.0, ge=0)
    """Scan points closer than this (the vehicle itself) are not used."""
    max_correspondence_m: float = Field(1.0, gt=0)
    """Correspondences farther apart than this are not used by the registration."""
    kernel_m: float = Field(0.3, gt=0)
    """Tukey kernel width of the point-to-plane residuals (m)."""
    max_iterations: int = Field(30, ge=1)
    """Registration iterations at most."""
    min_points: int = Field(200, ge=10)
    """A scan with fewer usable points is neither registered nor mapped."""
    keyframe_distance_m: float = Field(10.0, gt=0)
    """A new anchor keyframe when the sensor is this far from the current one: the factors
    are ``T_anchor_k`` (both poses in the local map), so errors add up per keyframe."""
    warmup_scans: int = Field(2, ge=1)
    """Scans mapped before the first registration (the map must hold something)."""
    rotation_std_deg: float = Field(0.05, gt=0)
    """1-sigma per axis of a map factor's rotation (deg) ..."""
    translation_std_m: float = Field(0.02, gt=0)
    """... and translation (m)."""
    odometry_covariance_scale: float = Field(16.0, ge=1)
    """The odometry factors' covariance is multiplied by this while the stage runs. A
    frontend's covariance describes the noise of one step, not its bias, which adds up
    along the chain (ssf: 0.1 % of each step on simulated dt, 0.5 % on kitti00-path); in
    A-LOAM the map registration, not the odometry, fixes the pose, and the odometry keeps
    the steps smooth. 1 = the frontend's own covariance (docs/mapping.md, measured)."""
    max_prior_rotation_deg: float = Field(2.0, gt=0)
    """A registration that moves the pose more than this from the odometry's is dropped ..."""
    max_prior_translation_m: float = Field(0.5, gt=0)
    """... or more than this (m): then no factor, and the map restarts at that scan."""

    @model_validator(mode="after")
    def _ranges(self) -> "MappingConfig":
        if self.min_range_m >= self.max_range_m:
            raise ValueError(f"mapping.min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")
        return self
