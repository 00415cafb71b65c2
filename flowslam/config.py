"""Typed configuration of a flowslam run (pydantic), loadable from / dumpable to YAML.

``flowslam config`` prints the defaults; ``flowslam run --config FILE`` loads a
file (any subset of keys); command-line options override the file. Units:
metres, seconds, radians -- except fields whose name says ``_deg``.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from flowslam.errors import InputError
from flowslam.backends.isam2 import Isam2Config
from flowslam.flow_odometry import FlowOdometryConfig
from flowslam.frontends.ssf import SsfConfig


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DatasetConfig(_Strict):
    format: str | None = None
    """Force a reader ('kitti', 'folder', 'rosbag', 'argoverse2'); None = guess from the path."""
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
    first_frame: int = 0
    max_frames: int | None = None


class KissIcpConfig(_Strict):
    """Options of the ``kiss-icp`` frontend (passed to the kiss-icp package)."""

    max_range: float = 100.0
    min_range: float = 0.0
    deskew: bool = True
    voxel_size: float | None = None
    """None: max_range / 100, as kiss-icp does."""
    max_points_per_voxel: int = 20
    rotation_std_deg: float = 0.1
    """kiss-icp reports no covariance: the odometry measurement gets this fixed 1-sigma (deg)."""
    translation_std_m: float = 0.05
    """... and this fixed 1-sigma translation (m) per axis."""


class OutputConfig(_Strict):
    """What a run writes besides the trajectories."""

    static_map: bool = True
    """Write ``static_map.ply`` (points marked dynamic removed, optimised poses)."""
    map_voxel_size: float = 0.2
    """Voxel size (m) of the static map."""
    map_points_per_frame: int = 10000
    """Points kept per scan for the map (memory: ~60 kB per scan)."""
    plot: bool = True


class PipelineConfig(_Strict):
    frontend: str = "kiss-icp"
    backend: str = "odometry"
    output_dir: Path = Path("results")
    dataset: DatasetConfig = DatasetConfig()
    output: OutputConfig = OutputConfig()
    kiss_icp: KissIcpConfig = KissIcpConfig()
    flow_odometry: FlowOdometryConfig = FlowOdometryConfig()
    isam2: Isam2Config = Isam2Config()
    ssf: SsfConfig = SsfConfig()


def load_config(path: Path | None = None, **overrides) -> PipelineConfig:
    """Defaults, updated from a YAML file (if given), then from non-None ``overrides``.

    Overrides use dotted names for nested fields, e.g. ``{"dataset.topic": "/points"}``.
    """
    data: dict = {}
    if path is not None:
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except FileNotFoundError:
            raise InputError(path, "config file does not exist") from None
        except (OSError, yaml.YAMLError) as e:
            raise InputError(path, f"cannot read config: {e}".splitlines()[0]) from None
        if not isinstance(data, dict):
            raise InputError(path, "config must be a YAML mapping")
    for dotted, value in overrides.items():
        if value is None:
            continue
        node = data
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    try:
        return PipelineConfig.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise InputError(path, f"config field {where!r}: {err['msg']}") from None


def dump_config(config: PipelineConfig) -> str:
    """YAML text of a config (paths as strings)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
