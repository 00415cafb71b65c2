"""Registration without an initial guess: FPFH features + Open3D RANSAC (+ optional ICP).

Shared by the ``ransac`` baseline frontend (:mod:`flowslam.frontends.ransac`, which adds
its covariance recipe and fallbacks) and the motion-fault recovery of ``ssf``
(:mod:`flowslam.registration.recovery`), which needs a start that does not depend on
the constant-velocity prior. The options are those of
:class:`flowslam.config.RansacConfig`; radii and distances left at None are the
multiples of the voxel of Open3D's global registration tutorial.

1. :meth:`FpfhRansac.features` (once per scan): points beyond ``max_range_m`` dropped,
   voxel downsampling, normals (radius 2 x voxel), FPFH (radius 5 x voxel).
2. :meth:`FpfhRansac.align`: ``registration_ransac_based_on_feature_matching`` of
   ``source`` onto ``target`` (mutual filter, ``ransac_n`` matches per hypothesis,
   edge-length and distance checkers, point-to-point estimation, distance 1.5 x voxel),
   Open3D's generator seeded with ``seed`` before every call (Open3D draws hypotheses in
   parallel threads, so identical calls can still differ slightly); then, with
   ``icp_refine``, point-to-plane ICP of the two downsampled clouds (distance 0.4 x voxel).

Frames: the result ``T_target_source`` (4x4, m) maps source points into the target's
frame; scan k as the source and scan k-1 as the target give ``T_prev_curr``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from flowslam.config.baselines import RansacConfig

__all__ = ["FpfhRansac", "GlobalAlignment", "ScanFeatures"]


@dataclass
class ScanFeatures:
    """A scan as RANSAC sees it: downsampled cloud (with normals) and its FPFH features."""

    cloud: object
    """``open3d.geometry.PointCloud`` (sensor frame of the scan, m), with normals."""
    features: object | None
    """``open3d.pipelines.registration.Feature`` (33 x N), None when too few points."""
    points: np.ndarray
    """(N,3) float64 array of the cloud's points."""
    timestamp: float


@dataclass
class GlobalAlignment:
    """Outcome of :meth:`FpfhRansac.align`.

    ``T_target_source`` (4x4): the RANSAC pose, or ICP's from it; ``pairs`` (M,2)
    [source index, target index] of the aligned points behind it (RANSAC's consensus or
    ICP's final correspondences); ``refined``: ICP ran; ``stats``: ``fitness``,
    ``inlier_rmse_m``, ``correspondences``, ``inliers`` (and ``icp_fitness``,
    ``icp_rmse_m``); ``laps``: ``ransac`` (and ``icp``) wall time in ms.
    """

    T_target_source: np.ndarray
    pairs: np.ndarray
    refined: bool
    stats: dict = field(default_factory=dict)
    laps: dict = field(default_factory=dict)


def _millis(start: float) -> float:
    return (time.perf_counter() - start) * 1e3


class FpfhRansac:
    """FPFH + RANSAC (+ ICP) with the options of a :class:`RansacConfig` (module doc)."""

    def __init__(self, options: RansacConfig | None = None):
        self.options = c = options or RansacConfig()
        voxel = c.voxel_size_m
        self.normal_radius_m = c.normal_radius_m or 2.0 * voxel
        """Normal search radius (m)."""
        self.fpfh_radius_m = c.fpfh_radius_m or 5.0 * voxel
        """FPFH search radius (m)."""
        self.distance_m = c.max_correspondence_distance_m or 1.5 * voxel
        """RANSAC inlier distance (m)."""
        self.icp_distance_m = c.icp_distance_m or 0.4 * voxel
        """ICP correspondence distance (m)."""

    def features(self, points: np.ndarray, timestamp: float = 0.0) -> ScanFeatures:
        """Crop, downsample, normals and FPFH of one scan ((N,3) points, sensor frame, m);
        ``features`` is None when fewer than ``min_points`` downsampled points remain."""
        import open3d as o3d

        c = self.options
        p = np.asarray(points, dtype=np.float64)
        p = p[np.einsum("ij,ij->i", p, p) < c.max_range_m**2]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(c.voxel_size_m)
        down = np.asarray(cloud.points)
        if len(down) < c.min_points:
            return ScanFeatures(cloud, None, down, timestamp)
        search = o3d.geometry.KDTreeSearchParamHybrid
        cloud.estimate_normals(search(radius=self.normal_radius_m, max_nn=c.normal_max_nn))
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            cloud, search(radius=self.fpfh_radius_m, max_nn=c.fpfh_max_nn))
        return ScanFeatures(cloud, fpfh, down, timestamp)

    def align(self, source: ScanFeatures, target: ScanFeatures) -> GlobalAlignment:
        """RANSAC of ``source`` onto ``target`` (both with features), then ICP with
        ``icp_refine`` when RANSAC aligned at least ``min_inliers`` pairs."""
        import open3d as o3d

        c = self.options
        reg = o3d.pipelines.registration
        checkers = []
        if c.edge_length_similarity > 0:
            checkers.append(reg.CorrespondenceCheckerBasedOnEdgeLength(c.edge_length_similarity))
        if c.distance_check:
            checkers.append(reg.CorrespondenceCheckerBasedOnDistance(self.distance_m))
        start = time.perf_counter()
        o3d.utility.random.seed(c.seed)
        result = reg.registration_ransac_based_on_feature_matching(
            source.cloud, target.cloud, source.features, target.features, c.mutual_filter, self.distance_m,
            reg.TransformationEstimationPointToPoint(False), c.ransac_n, checkers,
            reg.RANSACConvergenceCriteria(c.max_iterations, c.confidence))
        laps = {"ransac": _millis(start)}
        T = np.array(result.transformation, dtype=np.float64)
        pairs = np.asarray(result.correspondence_set, dtype=np.int64).reshape(-1, 2)
        stats = dict(fitness=float(result.fitness), inlier_rmse_m=float(result.inlier_rmse),
                     correspondences=len(pairs), inliers=len(pairs))
        if not c.icp_refine or len(pairs) < c.min_inliers:
            return GlobalAlignment(T, pairs, False, stats, laps)
        start = time.perf_counter()
        icp = reg.registration_icp(
            source.cloud, target.cloud, self.icp_distance_m, T, reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=c.icp_max_iterations))
        laps["icp"] = _millis(start)
        icp_pairs = np.asarray(icp.correspondence_set, dtype=np.int64).reshape(-1, 2)
        stats.update(icp_fitness=float(icp.fitness), icp_rmse_m=float(icp.inlier_rmse), inliers=len(icp_pairs))
        return GlobalAlignment(np.array(icp.transformation, dtype=np.float64), icp_pairs, True, stats, laps)
