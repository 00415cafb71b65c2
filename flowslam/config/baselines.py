"""Options of the baseline frontends that are not flowslam's own: ``ransac:``.

``ransac`` is SSF-PAN's default registration for A-LOAM / S-LOAM: FPFH features and
Open3D's RANSAC global registration of consecutive scans. The defaults are those of
Open3D's global registration tutorial, relative to the voxel size (normals 2x, FPFH
5x, RANSAC distance 1.5x, ICP 0.4x the voxel); ``None`` in a ``_m`` field means that
multiple of ``voxel_size_m``. Metres, except fields whose name says ``_deg``.
"""

from __future__ import annotations

from pydantic import Field

from flowslam.config.base import StrictModel


class RansacConfig(StrictModel):
    """Options of the ``ransac`` frontend (FPFH + Open3D RANSAC, scan k onto scan k-1).

    The constant-velocity fallback uses the ``flow_odometry`` section's
    ``fallback_*`` and ``no_prior_*`` options (one motion model for every frontend)."""

    voxel_size_m: float = Field(0.5, gt=0)
    """Voxel (m) of the downsampled clouds that features, RANSAC and ICP work on."""
    max_range_m: float = Field(100.0, gt=0)
    """Points farther than this from the sensor are dropped before downsampling (m)."""
    min_points: int = Field(100, ge=3)
    """Fewer downsampled points in either scan -> constant-velocity fallback (``few_points``)."""
    normal_radius_m: float | None = Field(None, gt=0)
    """Search radius (m) of the normals the FPFH features need; None: 2 x voxel_size_m."""
    normal_max_nn: int = Field(30, ge=3)
    """At most this many neighbours per normal."""
    fpfh_radius_m: float | None = Field(None, gt=0)
    """Search radius (m) of the FPFH features; None: 5 x voxel_size_m."""
    fpfh_max_nn: int = Field(100, ge=1)
    """At most this many neighbours per FPFH feature."""
    mutual_filter: bool = True
    """Keep only feature matches that are each other's nearest neighbour (Open3D's mutual filter)."""
    max_correspondence_distance_m: float | None = Field(None, gt=0)
    """RANSAC inlier distance (m) between aligned points; None: 1.5 x voxel_size_m."""
    ransac_n: int = Field(3, ge=3)
    """Feature matches per RANSAC hypothesis."""
    edge_length_similarity: float = Field(0.9, ge=0, lt=1)
    """Edge-length checker: the sampled matches' pairwise distances must agree to this ratio; 0 = off."""
    distance_check: bool = True
    """Distance checker: every sampled match must be within the RANSAC distance after alignment."""
    max_iterations: int = Field(100000, ge=1)
    """RANSAC hypotheses at most."""
    confidence: float = Field(0.999, gt=0, le=1)
    """RANSAC stops once it has found the best hypothesis with this probability (1: never early)."""
    seed: int = 0
    """Seed of Open3D's random generator, set before every registration (repeatable runs)."""
    min_fitness: float = Field(0.5, ge=0, le=1)
    """RANSAC fitness (share of scan k's points with a scan k-1 point within the RANSAC distance)
    below this -> constant-velocity fallback (``few_inliers``). Consecutive scans score ~0.9; a
    wrong pose that only aligns the ground plane ~0.4."""
    min_inliers: int = Field(100, ge=3)
    """Fewer aligned point pairs than this -> constant-velocity fallback (``few_inliers``)."""
    icp_refine: bool = False
    """Refine the RANSAC pose by point-to-plane ICP (off: the baseline as published)."""
    icp_distance_m: float | None = Field(None, gt=0)
    """ICP correspondence distance (m); None: 0.4 x voxel_size_m."""
    icp_max_iterations: int = Field(30, ge=1)
    """ICP iterations at most."""
    effective_samples: float = Field(3.0, gt=0)
    """Covariance x max(1, pairs / this): a RANSAC pose is fitted to ransac_n sampled matches,
    not to all aligned pairs, so they count as this many independent points."""
    icp_effective_samples: float = Field(100.0, gt=0)
    """The same after ICP refinement (a least-squares fit to all pairs, whose errors are correlated)."""
    good_fitness: float = Field(0.6, gt=0, le=1)
    """Fitness below this multiplies the covariance by (good_fitness / fitness)^2."""
    min_rotation_std_deg: float = Field(0.05, ge=0)
    """Added covariance floor, rotation 1-sigma per axis (deg)."""
    min_translation_std_m: float = Field(0.02, ge=0)
    """Added covariance floor, translation 1-sigma per axis (m)."""
