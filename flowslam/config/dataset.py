"""Options of the dataset readers (``dataset:`` in the run config)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from flowslam.config.base import StrictModel


class DatasetConfig(StrictModel):
    """Which reader opens a sequence and which part of it is processed."""

    format: str | None = None
    """Force a reader ('kitti', 'folder', 'rosbag', 'argoverse2', 'simulated'); None = guess from the path."""
    sequence: str | None = None
    """KITTI sequence id when the root holds several."""
    topic: str | None = None
    """ROS bags: the sensor_msgs/PointCloud2 topic (needed only when there are several)."""
    gt_topic: str | None = None
    """ROS bags: nav_msgs/Odometry or geometry_msgs/PoseStamped topic with GT poses."""
    poses: Path | None = None
    """Folder datasets: a KITTI or TUM GT poses file."""
    kitti_vertical_correction_deg: float | None = None
    """KITTI: beam elevation correction (deg); None = the reader's default 0.205, 0 = off."""
    first_frame: int = Field(0, ge=0)
    """Index of the first scan processed."""
    max_frames: int | None = Field(None, ge=1)
    """Process at most this many scans (None: to the end)."""
    max_coordinate_m: float = Field(1000.0, gt=0)
    """Plausible range (m): points with |x|, |y| or |z| beyond it (sensor frame) are dropped like NaN points and counted; a scan left with too few points is an input error."""
    fix_times: bool = False
    """Repair scan timestamps that do not increase strictly (each becomes the previous + the median interval, with a warning) instead of stopping with an error."""
