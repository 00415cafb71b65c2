"""Frontend ``kiss-icp``: the KISS-ICP odometry package as a flowslam frontend (baseline).

KISS-ICP registers each scan against its local voxel map; the change of its pose
between consecutive scans, ``T_prev_curr = inv(T_world_{k-1}) @ T_world_k``, is the
odometry measurement. KISS-ICP reports no uncertainty, so the measurement gets a
fixed diagonal covariance from the config (rotation first, then translation, as
GTSAM's Pose3 tangent). It produces no per-point flow or segmentation.
"""

from __future__ import annotations

import numpy as np

from flowslam import geometry
from flowslam.config import KissIcpConfig, PipelineConfig
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput


class KissIcpFrontend:
    """Wraps ``kiss_icp.kiss_icp.KissICP``; one instance per sequence (it keeps a map)."""

    name = "kiss-icp"
    config_sections = ("kiss_icp",)
    """The config sections it reads (an option of another section given on the command line is an error)."""

    def __init__(self, options: KissIcpConfig | None = None):
        from kiss_icp.config import load_config as load_kiss_config
        from kiss_icp.kiss_icp import KissICP

        options = options or KissIcpConfig()
        kiss_config = load_kiss_config(None)
        kiss_config.data.max_range = options.max_range
        kiss_config.data.min_range = options.min_range
        kiss_config.data.deskew = options.deskew
        kiss_config.mapping.voxel_size = options.voxel_size or options.max_range / 100.0
        kiss_config.mapping.max_points_per_voxel = options.max_points_per_voxel
        self._odometry = KissICP(kiss_config)
        self._covariance = geometry.pose_covariance(np.deg2rad(options.rotation_std_deg), options.translation_std_m)
        self._last_pose: np.ndarray | None = None

    def process(self, frame: Frame) -> FrontendOutput:
        times = frame.point_times if frame.point_times is not None else np.array([])
        self._odometry.register_frame(np.asarray(frame.points, dtype=np.float64), times)
        pose = np.array(self._odometry.last_pose, dtype=np.float64)
        if self._last_pose is None:
            T_prev_curr, cov = None, None
        else:
            T_prev_curr, cov = geometry.relative(self._last_pose, pose), self._covariance.copy()
        self._last_pose = pose
        return FrontendOutput(index=frame.index, T_prev_curr=T_prev_curr, covariance=cov)


def make_frontend(config: PipelineConfig) -> KissIcpFrontend:
    return KissIcpFrontend(config.kiss_icp)
