"""Write small ROS1 / ROS2 (sqlite3, mcap) bags of PointCloud2 scans and GT poses with ``rosbags``.

Used to build real bags for tests and benchmarks and to export scans. Message
classes come from ``rosbags.typesys`` (ROS1 Noetic or ROS2 Humble definitions);
stamps are integer nanoseconds; poses ``T_world_sensor`` (4x4, metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from flowslam import geometry
from flowslam.datasets.pointcloud2 import POINTCLOUD2, pack_points

BAG_KINDS = ("ros1", "sqlite3", "mcap")

DEFAULT_LAYOUT = (("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"))


@dataclass
class BagMessage:
    """One message to write: topic, ROS2-style type name, receive time (ns) and the message object."""

    topic: str
    msgtype: str
    timestamp_ns: int
    msg: Any


def typestore_for(kind: str):
    """The ``rosbags`` typestore matching a bag kind (ROS1 Noetic or ROS2 Humble)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


def _header(ts, stamp_ns: int, frame_id: str):
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    if any(name == "seq" for name, _ in ts.fielddefs["std_msgs/msg/Header"][1]):  # ROS1 header
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def make_pointcloud2(
    ts,
    stamp_ns: int,
    columns: Mapping[str, np.ndarray],
    layout: Sequence[tuple[str | None, str]] = DEFAULT_LAYOUT,
    *,
    frame_id: str = "lidar",
    big_endian: bool = False,
    height: int = 1,
    row_padding: int = 0,
):
    """A PointCloud2 message from per-point columns (see ``pack_points``).

    ``height > 1`` makes an organised cloud (N must divide by it); ``row_padding``
    adds that many unused bytes at the end of every row (``row_step > width*point_step``).
    """
    T = ts.types
    fields, step, data = pack_points(columns, layout, big_endian=big_endian)
    n = len(data) // step
    width = n // height
    if row_padding:
        rows = data.reshape(height, width * step)
        data = np.concatenate([rows, np.zeros((height, row_padding), np.uint8)], axis=1).reshape(-1)
    return T[POINTCLOUD2](
        header=_header(ts, stamp_ns, frame_id),
        height=height,
        width=width,
        fields=[T["sensor_msgs/msg/PointField"](name=a, offset=b, datatype=c, count=d) for a, b, c, d in fields],
        is_bigendian=big_endian,
        point_step=step,
        row_step=width * step + row_padding,
        data=data,
        is_dense=False,
    )


def make_pose_message(ts, msgtype: str, stamp_ns: int, T_world_sensor: np.ndarray, frame_id: str = "map",
                      child_frame_id: str = "lidar"):
    """A ``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/PoseStamped`` carrying a pose."""
    T = ts.types
    q = geometry.to_quat_xyzw(T_world_sensor)
    t = T_world_sensor[:3, 3]
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )
    header = _header(ts, stamp_ns, frame_id)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return T[msgtype](header=header, pose=pose)
    if msgtype == "nav_msgs/msg/Odometry":
        zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        return T[msgtype](
            header=header,
            child_frame_id=child_frame_id,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)
            ),
        )
    raise ValueError(f"unsupported pose message type {msgtype!r}")


def write_bag(path: str | Path, kind: str, messages: Iterable[BagMessage]) -> Path:
    """Write messages (in the given order) to a new bag; ``kind`` in ``BAG_KINDS``.

    ROS1 writes the file ``path`` (conventionally ``*.bag``); ROS2 kinds create the
    bag folder ``path`` with ``metadata.yaml``. Returns ``path``.
    """
    path = Path(path)
    ts = typestore_for(kind)
    if kind == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
        serialize = ts.serialize_ros1
    elif kind in ("sqlite3", "mcap"):
        from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        serialize = ts.serialize_cdr
    else:
        raise ValueError(f"unknown bag kind {kind!r} (use one of {BAG_KINDS})")
    connections: dict[str, Any] = {}
    with writer:
        for m in messages:
            if m.topic not in connections:
                connections[m.topic] = writer.add_connection(m.topic, m.msgtype, typestore=ts)
            writer.write(connections[m.topic], m.timestamp_ns, serialize(m.msg, m.msgtype))
    return path
