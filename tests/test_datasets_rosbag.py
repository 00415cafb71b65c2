"""RosBag: real ROS1 / ROS2 (sqlite3, mcap) bags written with rosbags from real KITTI scans.

Each bag kind uses a different PointCloud2 layout (padding, field order, float64 /
uint32-ns / absolute-seconds time, big-endian organised cloud with row padding) and
a GT pose topic sampled from an analytic motion (constant yaw rate about z, constant
velocity), for which linear-translation + slerp interpolation is exact.
"""

from __future__ import annotations

import logging
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from flowslam import geometry
from flowslam.datasets.pointcloud2 import decode_pointcloud2
from flowslam.datasets.rosbag import RosBag
from flowslam.datasets.rosbag_writer import BagMessage, make_pointcloud2, make_pose_message, typestore_for, write_bag
from flowslam.errors import InputError

PC2 = "sensor_msgs/msg/PointCloud2"
ODOM = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
T0 = 1_700_000_000_123_456_789  # ns
SCAN_STAMPS = [T0 + k * 100_000_000 for k in range(3)]
YAW_RATE, VEL = 0.2, np.array([5.0, 0.3, 0.0])  # rad/s, m/s


def true_pose(stamp_ns: int) -> np.ndarray:
    dt = (stamp_ns - T0) * 1e-9
    return geometry.from_euler("z", YAW_RATE * dt, VEL * dt + [0.0, 0.0, 0.1])


LAYOUTS = {
    # ROS1: padding, intensity first, float64 'time' (relative seconds) at an unaligned offset
    "ros1": dict(layout=[("intensity", "f4"), (None, "u4"), ("x", "f4"), ("y", "f4"), ("z", "f4"), (None, "u2"),
                         ("time", "f8")], gt=ODOM),
    # sqlite3: float64 xyz, uint32 't' in ns (Ouster style), uint16 ring, uint8 intensity, padding
    "sqlite3": dict(layout=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("t", "u4"), ("ring", "u2"), ("intensity", "u1"),
                            (None, "u1")], gt=POSE),
    # mcap: big-endian, organised 4 rows with 12 bytes of row padding, absolute float64 'timestamp' first
    "mcap": dict(layout=[("timestamp", "f8"), ("z", "f4"), ("x", "f4"), ("y", "f4"), ("intensity", "f4")],
                 gt=ODOM, big_endian=True, height=4, row_padding=12),
}


@pytest.fixture(scope="module")
def kitti_scans(kitti_extract: Path) -> list[dict[str, np.ndarray]]:
    """Three real KITTI scans (count a multiple of 4) with a spin-phase per-point time in [0, 0.1) s."""
    scans = []
    for i in range(3):
        rec = np.fromfile(kitti_extract / f"sequences/00/velodyne/{i:06d}.bin", dtype=np.float32).reshape(-1, 4)
        rec = rec[: len(rec) // 4 * 4]
        rel = ((np.arctan2(rec[:, 1], rec[:, 0]) + np.pi) / (2 * np.pi) * 0.1).astype(np.float64)
        scans.append({"x": rec[:, 0], "y": rec[:, 1], "z": rec[:, 2], "intensity": rec[:, 3], "rel": rel})
    return scans


def scan_columns(kind: str, scan: dict[str, np.ndarray], stamp: int) -> dict[str, np.ndarray]:
    cols = {k: scan[k] for k in ("x", "y", "z", "intensity")}
    if kind == "ros1":
        cols["time"] = scan["rel"]
    elif kind == "sqlite3":
        cols["t"] = np.round(scan["rel"] * 1e9).astype(np.uint32)
        cols["ring"] = np.arange(len(scan["x"])) % 64
        cols["intensity"] = np.round(scan["intensity"] * 255).astype(np.uint8)
    else:
        cols["timestamp"] = stamp * 1e-9 + scan["rel"]
    return cols


def gt_messages(ts, msgtype: str, start: int, stop: int, topic: str = "/gt") -> list[BagMessage]:
    stamps = range(start, stop, 30_000_000)  # 33 Hz, never on a scan stamp
    return [BagMessage(topic, msgtype, s, make_pose_message(ts, msgtype, s, true_pose(s))) for s in stamps]


def write_test_bag(path: Path, kind: str, scans, *, gt_start: int | None = None, extra_cloud: bool = False) -> Path:
    ts = typestore_for(kind)
    spec = LAYOUTS[kind]
    msgs = []
    for scan, stamp in zip(scans, SCAN_STAMPS):
        msg = make_pointcloud2(ts, stamp, scan_columns(kind, scan, stamp), spec["layout"],
                               big_endian=spec.get("big_endian", False), height=spec.get("height", 1),
                               row_padding=spec.get("row_padding", 0))
        msgs.append(BagMessage("/points", PC2, stamp + 7_000_000, msg))  # received 7 ms after the stamp
    if extra_cloud:
        small = {k: v[:200] for k, v in scans[0].items()}
        msgs.append(BagMessage("/aux_points", PC2, T0, make_pointcloud2(ts, T0, {k: small[k] for k in "xyz"},
                                                                        [("x", "f4"), ("y", "f4"), ("z", "f4")])))
    start = T0 - 45_000_000 if gt_start is None else gt_start
    msgs += gt_messages(ts, spec["gt"], start, SCAN_STAMPS[-1] + 50_000_000)
    msgs.sort(key=lambda m: m.timestamp_ns)
    return write_bag(path, kind, msgs)


@pytest.fixture(scope="module")
def bags(kitti_scans, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "ros1": write_test_bag(root / "scans.bag", "ros1", kitti_scans, extra_cloud=True),
        "sqlite3": write_test_bag(root / "scans_sqlite3", "sqlite3", kitti_scans),
        "mcap": write_test_bag(root / "scans_mcap", "mcap", kitti_scans),
    }


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_round_trip(bags, kitti_scans, kind: str):
    ds = RosBag(bags[kind], topic="/points" if kind == "ros1" else None, gt_topic="/gt")
    assert len(ds) == 3 and ds.topic == "/points"
    np.testing.assert_array_equal(ds.stamps_ns, SCAN_STAMPS)
    np.testing.assert_allclose(ds.timestamps, np.array(SCAN_STAMPS) * 1e-9, rtol=0, atol=1e-6)
    frames = list(ds)
    for k, (frame, scan) in enumerate(zip(frames, kitti_scans)):
        assert frame.source == f"{ds.bag_path} [/points #{k}]"
        assert frame.timestamp == pytest.approx(SCAN_STAMPS[k] * 1e-9, abs=1e-6)
        xyz = np.column_stack([scan["x"], scan["y"], scan["z"]]).astype(np.float64)
        np.testing.assert_array_equal(frame.points, xyz)
        want_i = np.round(scan["intensity"] * 255) if kind == "sqlite3" else scan["intensity"].astype(np.float64)
        np.testing.assert_array_equal(frame.intensity, want_i)
        time_tol = {"ros1": 0.0, "sqlite3": 0.6e-9, "mcap": 1e-6}[kind]
        np.testing.assert_allclose(frame.point_times, scan["rel"], rtol=0, atol=time_tol)
        np.testing.assert_allclose(frame.gt_pose, true_pose(SCAN_STAMPS[k]), rtol=0, atol=1e-9)
    assert ds.gt.valid.all()
    np.testing.assert_allclose(ds.gt_poses, np.stack([true_pose(s) for s in SCAN_STAMPS]), rtol=0, atol=1e-9)
    # random access, in any order, equals the streamed frames; and survives close/reopen
    for k in (2, 0, 1):
        np.testing.assert_array_equal(ds[k].points, frames[k].points)
    ds.close()
    np.testing.assert_array_equal(ds[1].point_times, frames[1].point_times)
    ds.close()


def test_partial_gt_coverage(kitti_scans, tmp_path: Path, caplog):
    bag = write_test_bag(tmp_path / "late_gt", "sqlite3", kitti_scans, gt_start=SCAN_STAMPS[0] + 20_000_000)
    with caplog.at_level(logging.WARNING):
        ds = RosBag(bag, gt_topic="/gt")
    assert "GT poses cover only 2 of 3 scans" in caplog.text
    assert ds.gt_poses is None
    np.testing.assert_array_equal(ds.gt.valid, [False, True, True])
    assert ds[0].gt_pose is None
    np.testing.assert_allclose(ds[2].gt_pose, true_pose(SCAN_STAMPS[2]), rtol=0, atol=1e-9)
    assert np.isnan(ds.gt.partial[0]).all()


def test_same_receive_time_messages(kitti_scans, tmp_path: Path):
    ts = typestore_for("mcap")
    small = {k: v[:300] for k, v in kitti_scans[0].items()}
    msgs = []
    for k in range(3):
        cols = {"x": small["x"] + k, "y": small["y"], "z": small["z"]}
        msgs.append(BagMessage("/points", PC2, T0, make_pointcloud2(ts, T0 + k, cols, [("x", "f4"), ("y", "f4"), ("z", "f4")])))
    ds = RosBag(write_bag(tmp_path / "same", "mcap", msgs))
    np.testing.assert_array_equal(ds.stamps_ns, [T0, T0 + 1, T0 + 2])
    for k in (2, 1, 0):
        np.testing.assert_allclose(ds[k].points[:, 0], small["x"].astype(np.float64) + k, rtol=0, atol=1e-5)
    ds.close()


def test_hand_packed_big_endian_message(kitti_scans):
    """Bytes packed point by point with struct (independent of the writer's packing)."""
    T = typestore_for("mcap").types
    n, height, width, pad = 150, 3, 50, 5
    scan = {k: v[:n] for k, v in kitti_scans[1].items()}
    abs_s = T0 * 1e-9 + scan["rel"]  # absolute float64 seconds
    # layout: float64 'timestamp' @0, float32 normal[3] @8, float32 z @20, x @24, y @28, uint16 intensity @32
    step = 34
    rows = []
    for r in range(height):
        row = b"".join(
            struct.pack(">d3ffffH", abs_s[i], 0.0, 0.0, 1.0, scan["z"][i], scan["x"][i], scan["y"][i],
                        int(scan["intensity"][i] * 1000))
            for i in range(r * width, (r + 1) * width)
        )
        rows.append(row + b"\xee" * pad)
    F = T["sensor_msgs/msg/PointField"]
    msg = T[PC2](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=T0 // 10**9, nanosec=T0 % 10**9),
                                        frame_id="velo"),
        height=height, width=width,
        fields=[F(name="timestamp", offset=0, datatype=8, count=1), F(name="normal", offset=8, datatype=7, count=3),
                F(name="z", offset=20, datatype=7, count=1), F(name="x", offset=24, datatype=7, count=1),
                F(name="y", offset=28, datatype=7, count=1), F(name="intensity", offset=32, datatype=4, count=1)],
        is_bigendian=True, point_step=step, row_step=width * step + pad,
        data=np.frombuffer(b"".join(rows), dtype=np.uint8), is_dense=True,
    )
    cloud = decode_pointcloud2(msg, "test")
    xyz = np.column_stack([scan["x"], scan["y"], scan["z"]]).astype(np.float64)
    np.testing.assert_array_equal(cloud.points, xyz)
    np.testing.assert_array_equal(cloud.intensity, np.array([int(v * 1000) for v in scan["intensity"]], float))
    np.testing.assert_allclose(cloud.point_times, scan["rel"], rtol=0, atol=1e-6)
    # a truncated buffer is an InputError naming the message
    msg.data = msg.data[:-40]
    with pytest.raises(InputError, match=r"^msg #3: PointCloud2 data has \d+ bytes"):
        decode_pointcloud2(msg, "msg #3")


def test_several_and_unknown_topics(bags):
    bag = bags["ros1"]
    with pytest.raises(InputError) as err:
        RosBag(bag)
    assert err.value.where == str(bag)
    assert "several PointCloud2 topics (/aux_points, /points); pick one with --topic (topic= in Python)" in err.value.problem
    with pytest.raises(InputError) as err:
        RosBag(bag, topic="/lidar")
    assert err.value.where == str(bag)
    assert err.value.problem == "topic '/lidar': has no such topic (PointCloud2 topics: /aux_points, /points)"
    with pytest.raises(InputError, match=r"topic '/gt': is not a PointCloud2 topic"):
        RosBag(bag, topic="/gt")
    with pytest.raises(InputError, match=r"GT topic '/points' has type sensor_msgs/msg/PointCloud2; supported"):
        RosBag(bag, topic="/points", gt_topic="/points")
    with pytest.raises(InputError, match=r"GT topic '/odom' does not exist"):
        RosBag(bag, topic="/points", gt_topic="/odom")


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_bag_without_pointcloud2(tmp_path: Path, kind: str):
    ts = typestore_for(kind)
    path = write_bag(tmp_path / ("odom.bag" if kind == "ros1" else "odom"), kind, gt_messages(ts, ODOM, T0, T0 + 10**8, "/odom"))
    with pytest.raises(InputError) as err:
        RosBag(path)
    assert err.value.where == str(path)
    assert err.value.problem == "has no sensor_msgs/msg/PointCloud2 topic (topics: /odom)"


def test_cloud_without_z(tmp_path: Path, kitti_scans):
    ts = typestore_for("sqlite3")
    scan = kitti_scans[0]
    msg = make_pointcloud2(ts, T0, {"x": scan["x"], "y": scan["y"], "intensity": scan["intensity"]},
                           [("x", "f4"), ("y", "f4"), ("intensity", "f4")])
    ds = RosBag(write_bag(tmp_path / "noz", "sqlite3", [BagMessage("/points", PC2, T0, msg)]))
    with pytest.raises(InputError) as err:
        ds[0]
    assert err.value.where == f"{tmp_path / 'noz'} [/points #0]"
    assert "PointCloud2 has no field(s) ['z'] (fields: ['x', 'y', 'intensity'])" in err.value.problem
    ds.close()


def test_broken_bags(tmp_path: Path, bags):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    with pytest.raises(InputError) as err:
        RosBag(junk)
    assert err.value.where == str(junk) and err.value.problem.startswith("cannot open bag")
    no_meta = tmp_path / "no_meta"
    shutil.copytree(bags["sqlite3"], no_meta)
    (no_meta / "metadata.yaml").unlink()
    with pytest.raises(InputError, match=r"no_meta: ROS2 bag folder has no metadata.yaml"):
        RosBag(no_meta)
    with pytest.raises(InputError, match="does not exist"):
        RosBag(tmp_path / "missing.bag")
    db3 = next(bags["sqlite3"].glob("*.db3"))
    ds = RosBag(db3)  # a storage file inside a bag folder opens the folder
    assert ds.bag_path == bags["sqlite3"] and len(ds) == 3
    ds.close()


@pytest.mark.parametrize(
    "name,code,encode,tol",
    [
        ("offset_time", "u4", lambda rel, stamp: np.round(rel * 1e9), 0.6e-9),  # Livox CustomMsg style ns
        ("time", "f4", lambda rel, stamp: rel, 1e-8),  # Velodyne style relative seconds
        ("timestamp", "f8", lambda rel, stamp: stamp * 1e-9 + rel, 1e-6),  # Hesai style epoch seconds
        ("timestamp", "f8", lambda rel, stamp: stamp + rel * 1e9, 1e-6),  # Livox PointCloud2 style epoch ns
        ("time_offset", "i4", lambda rel, stamp: np.round(rel * 1e9), 0.6e-9),
    ],
)
def test_time_field_rules(kitti_scans, name, code, encode, tol):
    ts = typestore_for("sqlite3")
    scan = {k: v[:500] for k, v in kitti_scans[2].items()}
    cols = {"x": scan["x"], "y": scan["y"], "z": scan["z"], name: encode(scan["rel"], T0)}
    msg = make_pointcloud2(ts, T0, cols, [("x", "f4"), ("y", "f4"), ("z", "f4"), (name, code)])
    cloud = decode_pointcloud2(msg, "m")
    assert cloud.intensity is None
    np.testing.assert_allclose(cloud.point_times, scan["rel"], rtol=0, atol=tol)


def test_pose_interpolation_edges():
    from flowslam.datasets.pose_interpolation import interpolate_poses, sorted_unique_poses

    stamps = np.array([3 * 10**9, 10**9, 2 * 10**9, 2 * 10**9], dtype=np.int64)  # unsorted, one repeat
    poses = np.stack([true_pose(T0 + int(s)) for s in stamps])
    poses[3] = np.eye(4)  # the repeated stamp's second sample is dropped
    s, p = sorted_unique_poses(stamps, poses)
    np.testing.assert_array_equal(s, [10**9, 2 * 10**9, 3 * 10**9])
    query = np.array([10**9, 3 * 10**9, 1_250_000_000, 10**9 - 1, 3 * 10**9 + 1], dtype=np.int64)
    out, valid = interpolate_poses(s, p, query)
    np.testing.assert_array_equal(valid, [True, True, True, False, False])
    np.testing.assert_array_equal(out[0], p[0])  # exact stamps are copied, not recomputed
    np.testing.assert_array_equal(out[1], p[2])
    np.testing.assert_allclose(out[2], true_pose(T0 + 1_250_000_000), rtol=0, atol=1e-12)
    assert np.isnan(out[3:]).all()
    # float seconds work the same way
    out_s, valid_s = interpolate_poses(s * 1e-9, p, query * 1e-9)
    np.testing.assert_array_equal(valid_s, valid)
    np.testing.assert_allclose(out_s[:3], out[:3], rtol=0, atol=1e-9)
