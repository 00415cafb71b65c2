"""Every bad input: one line naming the file and the problem, exit code 2, no traceback,
and (mid-sequence) the trajectory of the frames already processed is written."""

import json

import numpy as np
import pytest

from flowslam.trajectory import read_trajectory

from cli_helpers import assert_one_line_error, flowslam, write_kitti_bins


def run(seq, out, *extra):
    return flowslam("run", "--no-progress", "-o", out, *extra, seq)


def test_missing_path(tmp_path):
    assert_one_line_error(run(tmp_path / "nope", tmp_path / "r"), str(tmp_path / "nope"), "does not exist")


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_one_line_error(run(tmp_path / "empty", tmp_path / "r"), str(tmp_path / "empty"), "no scans")


def test_truncated_bin_keeps_the_frames_before(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 5)
    data = scans[3].read_bytes()
    scans[3].write_bytes(data[: len(data) - 7])
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert_one_line_error(proc, str(scans[3]), "multiple of 16")
    latest = tmp_path / "r" / "latest"
    assert len(read_trajectory(latest / "trajectory_tum.txt")) == 3
    info = json.loads((latest / "run.json").read_text())
    assert info["frames_processed"] == 3 and info["failed_index"] == 3 and "multiple of 16" in info["error"]


def test_truncated_bin_with_ssf_reading_ahead_keeps_the_frames_before(kitti_extract, tmp_path):
    """``ssf`` with two threads: the run loop reads scan k+1 early for the frontend; a bad
    scan there must still stop the run at its own turn, with every scan before it kept."""
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 5)
    data = scans[3].read_bytes()
    scans[3].write_bytes(data[: len(data) - 7])
    proc = run(tmp_path / "seq", tmp_path / "r", "-f", "ssf")
    assert_one_line_error(proc, str(scans[3]), "multiple of 16")
    latest = tmp_path / "r" / "latest"
    assert len(read_trajectory(latest / "trajectory_tum.txt")) == 3
    assert json.loads((latest / "run.json").read_text())["failed_index"] == 3


def test_nonfinite_points_are_dropped_and_counted(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    rec = np.fromfile(scans[1], dtype=np.float32).reshape(-1, 4)
    rec[:30, 0] = np.nan
    rec[30:50, 2] = np.inf
    rec.tofile(scans[1])
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert proc.returncode == 0, proc.stderr
    assert "dropped 50 points with NaN/inf" in proc.stderr and str(scans[1]) in proc.stderr


def test_scan_with_too_few_points(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    np.fromfile(scans[2], dtype=np.float32).reshape(-1, 4)[:80].tofile(scans[2])
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert_one_line_error(proc, str(scans[2]), "only 80 valid points")
    assert len(read_trajectory(tmp_path / "r" / "latest" / "trajectory_kitti.txt")) == 2


@pytest.mark.parametrize(
    "content, problem",
    [(b"\x00\xff\xfe garbage \x81\n", "cannot read"), (b"1 0 0 0 0 1 0 0 0 0 1 0\n" * 2, "has 2 poses but the folder has 3 scans")],
    ids=["unreadable", "wrong-length"],
)
def test_bad_poses_file(kitti_extract, tmp_path, content, problem):
    write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    poses = tmp_path / "seq" / "poses.txt"
    poses.write_bytes(content)
    assert_one_line_error(run(tmp_path / "seq", tmp_path / "r"), str(poses), problem)


def test_kitti_poses_file_of_wrong_length(kitti_extract, tmp_path):
    root = tmp_path / "kitti"
    write_kitti_bins(kitti_extract, root / "sequences" / "00" / "velodyne", 4)
    (root / "sequences" / "00" / "calib.txt").write_text((kitti_extract / "sequences/00/calib.txt").read_text())
    (root / "poses").mkdir()
    lines = (kitti_extract / "poses" / "00.txt").read_text().splitlines()
    (root / "poses" / "00.txt").write_text("\n".join(lines[:3]) + "\n")
    assert_one_line_error(run(root, tmp_path / "r"), str(root / "poses" / "00.txt"), "3")


def _write_bag(tmp_path, kitti_extract, topics):
    from flowslam.datasets.rosbag_writer import BagMessage, make_pointcloud2, make_pose_message, typestore_for, write_bag

    ts = typestore_for("mcap")
    rec = np.fromfile(kitti_extract / "sequences/00/velodyne/000000.bin", dtype=np.float32).reshape(-1, 4)[::8]
    cols = {"x": rec[:, 0], "y": rec[:, 1], "z": rec[:, 2], "intensity": rec[:, 3]}
    msgs = []
    for k in range(2):
        stamp = 1_700_000_000_000_000_000 + k * 100_000_000
        for topic in topics:
            msgs.append(BagMessage(topic, "sensor_msgs/msg/PointCloud2", stamp, make_pointcloud2(ts, stamp, cols)))
        msgs.append(BagMessage("/odom", "nav_msgs/msg/Odometry", stamp,
                               make_pose_message(ts, "nav_msgs/msg/Odometry", stamp, np.eye(4))))
    return write_bag(tmp_path / "bag", "mcap", msgs)


def test_bag_without_pointcloud2(kitti_extract, tmp_path):
    bag = _write_bag(tmp_path, kitti_extract, topics=[])
    assert_one_line_error(run(bag, tmp_path / "r"), str(bag), "no sensor_msgs/msg/PointCloud2")


def test_unknown_topic(kitti_extract, tmp_path):
    bag = _write_bag(tmp_path, kitti_extract, topics=["/velodyne_points"])
    line = assert_one_line_error(run(bag, tmp_path / "r", "--topic", "/points"), str(bag), "/points")
    assert "/velodyne_points" in line  # tells the user what exists


def test_several_clouds_need_a_topic(kitti_extract, tmp_path):
    bag = _write_bag(tmp_path, kitti_extract, topics=["/a", "/b"])
    assert_one_line_error(run(bag, tmp_path / "r"), str(bag), "--topic")


def test_unknown_frontend_and_bad_config(kitti_extract, tmp_path):
    assert_one_line_error(run(kitti_extract, tmp_path / "r", "--frontend", "nope"), "unknown frontend 'nope'")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("kiss_icp: {max_range: far}\n")
    assert_one_line_error(run(kitti_extract, tmp_path / "r", "-c", cfg), str(cfg), "max_range")


def test_misaligned_network_grid_crop(kitti_extract, tmp_path):
    """``ssf.network.grid_half_extent_m`` must take whole coarsest U-Net cells (12.8 m) off the
    shipped weights' 51.2 m grid: one line naming the option and the allowed step."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("ssf: {network: {grid_half_extent_m: 40.0}}\n")
    line = assert_one_line_error(run(kitti_extract, tmp_path / "r", "-f", "ssf", "-c", cfg),
                                 "ssf.network.grid_half_extent_m", "12.8 m")
    assert "40 m" in line


def test_debug_shows_the_traceback(tmp_path):
    proc = flowslam("--debug", "run", "--no-progress", "-o", tmp_path / "r", tmp_path / "nope")
    assert proc.returncode != 0 and "Traceback" in proc.stderr
