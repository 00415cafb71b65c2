"""ROS bag reader: PointCloud2 scans (+ optional GT pose topic) from ROS1 ``.bag`` files and
ROS2 bag folders (sqlite3 ``.db3`` or ``.mcap`` storage), through ``rosbags.highlevel.AnyReader``.

Frames and units: points are in the cloud's ``header.frame_id`` frame (the *sensor
frame*), metres. ``timestamp`` is the header stamp in seconds; ``point_times`` are
seconds relative to it (rule in ``flowslam.datasets.pointcloud2``). Frames are in
bag (receive) order; their header stamps must increase strictly in that order (else
``InputError`` naming the bag, topic and message index, or with ``fix_times`` a logged
repair, ``flowslam.trajectory.checked_timestamps``, applied before the GT lookup).

Ground truth: ``gt_topic`` may carry ``nav_msgs/msg/Odometry``,
``geometry_msgs/msg/PoseStamped``, ``PoseWithCovarianceStamped`` or
``TransformStamped``; each gives ``T_world_body`` at its header stamp, and
``T_world_sensor = T_world_body @ T_body_sensor`` (identity unless given: no TF
lookup is done). Poses are interpolated to every scan's header stamp (linear
translation, slerp rotation). Scans outside the GT time range get no pose: their
``Frame.gt_pose`` is None, and the dataset-level ``gt_poses`` is None unless every
scan is covered; ``RosBag.gt`` (a ``ScanPoses``) keeps the partial poses and the
``valid`` mask.

Memory: opening reads the scan topic once to index it, keeping only each
message's receive time and header stamp; a frame is re-read lazily by time
(``AnyReader.messages(start, stop)``). Iterating streams the topic in one pass.
The bag stays open until ``close()`` (or use ``with RosBag(...) as ds``).
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from flowslam import geometry
from flowslam.frame import Dataset, Frame
from flowslam.datasets.pointcloud2 import POINTCLOUD2, decode_pointcloud2, stamp_to_ns
from flowslam.datasets.pose_interpolation import ScanPoses, poses_at_scans
from flowslam.errors import InputError
from flowslam.trajectory import checked_timestamps, unit_quaternions

log = logging.getLogger(__name__)

ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")


def _pose_of(msg: Any, msgtype: str) -> tuple[Any, Any]:
    """(position-like, orientation-like) of a supported GT message."""
    if msgtype == "nav_msgs/msg/Odometry":
        return msg.pose.pose.position, msg.pose.pose.orientation
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return msg.pose.position, msg.pose.orientation
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        return msg.pose.pose.position, msg.pose.pose.orientation
    return msg.transform.translation, msg.transform.rotation  # TransformStamped


GT_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
)


def resolve_bag_path(path: Path) -> Path:
    """The path ``AnyReader`` wants: a ROS1 ``.bag`` file or a ROS2 folder with ``metadata.yaml``.

    A ROS2 storage file (``.db3``/``.mcap``) is accepted when its folder has ``metadata.yaml``.
    """
    if not path.exists():
        raise InputError(path, "does not exist")
    if path.is_file():
        if path.suffix == ".bag":
            return path
        if path.suffix in ROS2_STORAGE_SUFFIXES:
            if (path.parent / "metadata.yaml").is_file():
                return path.parent
            raise InputError(path, "ROS2 storage file without metadata.yaml next to it; pass the bag folder")
        raise InputError(path, "not a ROS bag (expected a .bag file or a ROS2 bag folder)")
    if (path / "metadata.yaml").is_file():
        return path
    if any(p.suffix in ROS2_STORAGE_SUFFIXES for p in path.iterdir()):
        raise InputError(path, "ROS2 bag folder has no metadata.yaml (needed to read it)")
    raise InputError(path, "not a ROS bag folder (no metadata.yaml)")


def _header_stamp_ns(raw: bytes | memoryview, is_ros2: bool) -> int:
    """Header stamp (ns) of a serialized message whose first field is ``std_msgs/Header``.

    ROS2 CDR: 4-byte encapsulation (byte 1: 0 big-, 1 little-endian), then int32
    sec, uint32 nanosec. ROS1: little-endian uint32 seq, uint32 sec, uint32 nsec.
    """
    if is_ros2:
        order = "<" if raw[1] & 1 else ">"
        sec, nsec = struct.unpack_from(order + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


def deserialize_message(deserialize: Callable[[Any, str], Any], raw: Any, msgtype: str, where: str) -> Any:
    """``deserialize(raw, msgtype)``; a corrupt message (whatever the deserializer raises on it)
    is an ``InputError`` naming ``where``."""
    try:
        return deserialize(raw, msgtype)
    except Exception as e:  # noqa: BLE001 - the deserializer's failures on bad bytes are not typed
        raise InputError(where, f"cannot deserialize {msgtype} ({e.__class__.__name__}: {e})") from None


def _bag_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    return (AnyReaderError, Reader1Error, Reader2Error, OSError, ValueError, KeyError, struct.error)


class RosBag(Dataset):
    """PointCloud2 scans from a ROS1/ROS2 bag (see module doc for frames, GT and memory).

    Args:
        path: a ROS1 ``.bag`` file, a ROS2 bag folder, or a storage file inside one.
        topic: the PointCloud2 topic; optional when the bag has exactly one.
        gt_topic: optional GT pose topic (Odometry / PoseStamped / ...).
        T_body_sensor: optional 4x4 extrinsic from the sensor into the GT body frame.
        fix_times: repair header stamps that do not increase strictly instead of raising.
    """

    name = "rosbag"

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        gt_topic: str | None = None,
        T_body_sensor: np.ndarray | None = None,
        fix_times: bool = False,
    ):
        super().__init__(path)
        self.fix_times = fix_times
        self.bag_path = resolve_bag_path(self.path)
        self._errors = _bag_errors()
        self._reader: Any = None
        self.topic: str | None = None
        self.gt_topic = gt_topic
        self.gt: ScanPoses | None = None
        reader = self._open()
        try:
            self.is_ros2 = reader.is2
            topics = {name: info.msgtype for name, info in reader.topics.items()}
            self.topic = self._choose_topic(topics, topic)
            self._connections = [c for c in reader.connections if c.topic == self.topic]
            self._index_scans()
            self.timestamps = self.stamps_ns * 1e-9
            if gt_topic is not None:
                self._read_gt(topics, gt_topic, T_body_sensor)
        except BaseException:
            self.close()
            raise

    # -- opening and indexing ------------------------------------------------------------
    def _open(self):
        if self._reader is None:
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore

            try:
                reader = AnyReader([self.bag_path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
                reader.open()
            except self._errors as e:
                raise InputError(self.bag_path, f"cannot open bag ({e.__class__.__name__}: {e})") from None
            self._reader = reader
            if self.topic is not None:  # reopened: connections belong to the reader instance
                self._connections = [c for c in reader.connections if c.topic == self.topic]
        return self._reader

    @staticmethod
    def _read_error(where: str | Path, what: str, e: BaseException) -> InputError:
        return InputError(where, f"cannot read {what} ({e.__class__.__name__}: {e})")

    def _choose_topic(self, topics: dict[str, str], topic: str | None) -> str:
        clouds = sorted(t for t, typ in topics.items() if typ == POINTCLOUD2)
        if topic is None:
            if not clouds:
                listed = ", ".join(sorted(topics)) or "none"
                raise InputError(self.bag_path, f"has no {POINTCLOUD2} topic (topics: {listed})")
            if len(clouds) > 1:
                raise InputError(
                    self.bag_path, f"has several PointCloud2 topics ({', '.join(clouds)}); pick one with --topic (topic= in Python)"
                )
            return clouds[0]
        if topics.get(topic) != POINTCLOUD2:
            what = "is not a PointCloud2 topic" if topic in topics else "has no such topic"
            raise InputError(
                self.bag_path, f"topic {topic!r}: {what} (PointCloud2 topics: {', '.join(clouds) or 'none'})"
            )
        return topic

    def _index_scans(self) -> None:
        """One pass over the topic: receive times, their ordinal among equal times, header stamps."""
        bag_t, stamps = [], []
        try:
            for _conn, t, raw in self._reader.messages(connections=self._connections):
                bag_t.append(t)
                stamps.append(_header_stamp_ns(raw, self.is_ros2))
        except self._errors as e:
            raise self._read_error(self.bag_path, f"topic {self.topic}", e) from None
        if not bag_t:
            raise InputError(self.bag_path, f"topic {self.topic} has no messages")
        self.bag_times_ns = np.array(bag_t, dtype=np.int64)
        same = np.r_[False, self.bag_times_ns[1:] == self.bag_times_ns[:-1]]
        run_start = np.maximum.accumulate(np.where(~same, np.arange(len(same)), 0))
        self._ordinal = np.arange(len(same)) - run_start
        self.stamps_ns = checked_timestamps(np.array(stamps, dtype=np.int64), f"{self.bag_path} [{self.topic}]",
                                            fix=self.fix_times, what="header stamps (ns)")

    def _read_gt(self, topics: dict[str, str], gt_topic: str, T_body_sensor: np.ndarray | None) -> None:
        typ = topics.get(gt_topic)
        if typ not in GT_TYPES:
            what = f"has type {typ}" if typ else "does not exist"
            raise InputError(self.bag_path, f"GT topic {gt_topic!r} {what}; supported: {', '.join(GT_TYPES)}")
        conns = [c for c in self._reader.connections if c.topic == gt_topic]
        stamps, quats, trans = [], [], []
        try:
            for conn, _t, raw in self._reader.messages(connections=conns):
                msg = self._reader.deserialize(raw, conn.msgtype)
                p, q = _pose_of(msg, typ)
                stamps.append(stamp_to_ns(msg.header.stamp))
                quats.append((q.x, q.y, q.z, q.w))
                trans.append((p.x, p.y, p.z))
        except self._errors as e:
            raise self._read_error(self.bag_path, f"GT topic {gt_topic}", e) from None
        if not stamps:
            raise InputError(self.bag_path, f"GT topic {gt_topic} has no messages")
        if not np.isfinite(trans).all():
            raise InputError(self.bag_path, f"GT topic {gt_topic} has a zero or non-finite pose")
        q = unit_quaternions(np.array(quats), self.bag_path, f"GT topic {gt_topic}")
        poses = geometry.from_quat_xyzw(q, np.array(trans, dtype=np.float64))
        if T_body_sensor is not None:
            poses = poses @ np.asarray(T_body_sensor, dtype=np.float64)
        where = f"{self.bag_path} [{gt_topic}]"
        self.gt = poses_at_scans(np.array(stamps, dtype=np.int64), poses, self.stamps_ns, where)
        self.gt_poses = self.gt.full

    # -- frames ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.bag_times_ns)

    def _source(self, index: int) -> str:
        return f"{self.bag_path} [{self.topic} #{index}]"

    def _frame(self, index: int, conn: Any, raw: bytes) -> Frame:
        where = self._source(index)
        msg = deserialize_message(self._reader.deserialize, raw, conn.msgtype, where)
        cloud = decode_pointcloud2(msg, where)
        gt = None if self.gt is None else self.gt.at(index)
        return Frame(
            index=index,
            timestamp=float(self.stamps_ns[index]) * 1e-9,
            points=cloud.points,
            intensity=cloud.intensity,
            point_times=cloud.point_times,
            gt_pose=gt,
            source=where,
            extras={"frame_id": msg.header.frame_id, "stamp_ns": int(self.stamps_ns[index])},
        )

    def _load(self, index: int) -> Frame:
        self._open()
        t = int(self.bag_times_ns[index])
        wanted = int(self._ordinal[index])
        stream = self._reader.messages(connections=self._connections, start=t, stop=t + 1)
        try:
            for k, (conn, _t, raw) in enumerate(stream):
                if k == wanted:
                    return self._frame(index, conn, raw)
        except self._errors as e:
            raise self._read_error(self._source(index), "message", e) from None
        finally:
            stream.close()
        raise InputError(self._source(index), "message vanished from the bag since it was indexed")

    def __iter__(self) -> Iterator[Frame]:
        """Stream all frames in one pass over the bag (faster than indexing one by one)."""
        self._open()
        try:
            stream = self._reader.messages(connections=self._connections)
            for index, (conn, _t, raw) in enumerate(stream):
                yield self.sanitized(self._frame(index, conn, raw))
        except self._errors as e:
            raise self._read_error(self.bag_path, f"topic {self.topic}", e) from None

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Close the bag; a later frame access reopens it."""
        if self._reader is not None:
            reader, self._reader = self._reader, None
            reader.close()

    def __enter__(self) -> "RosBag":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - never raise from a finalizer
            pass

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_reader"] = None
        return state
