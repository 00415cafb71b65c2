"""What is read is validated, not only how much (issue 15, part 1): PCD header/data
consistency, a plausible coordinate range, strictly increasing timestamps (or an explicit
``fix_times`` repair), malformed trajectory files. Inputs are made from the real KITTI
extract; CLI cases run the real ``flowslam`` command in a subprocess."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

import fuzz_inputs
from cli_helpers import assert_one_line_error, flowslam, write_kitti_bins

from flowslam.config.dataset import DatasetConfig
from flowslam.datasets import open_dataset
from flowslam.datasets.pcd import read_pcd
from flowslam.errors import InputError
from flowslam.trajectory import checked_timestamps, read_trajectory


def run(seq, out, *extra):
    return flowslam("run", "--no-progress", "-o", out, *extra, seq)


def kitti_points(kitti_extract: Path, i: int = 0, every: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rec = np.fromfile(kitti_extract / f"sequences/00/velodyne/{i:06d}.bin", dtype=np.float32).reshape(-1, 4)[::every]
    return rec[:, :3].copy(), rec[:, 3].copy()


def make_kitti(kitti_extract: Path, root: Path, n: int, times: list[float] | None = None) -> Path:
    """A KITTI layout with the first ``n`` real scans (every 4th point), calib, GT poses and times."""
    seq = root / "sequences" / "00"
    write_kitti_bins(kitti_extract, seq / "velodyne", n)
    shutil.copy(kitti_extract / "sequences/00/calib.txt", seq / "calib.txt")
    real_times = (kitti_extract / "sequences/00/times.txt").read_text().split()[:n]
    (seq / "times.txt").write_text("\n".join(map(str, times)) + "\n" if times else "\n".join(real_times) + "\n")
    (root / "poses").mkdir()
    lines = (kitti_extract / "poses/00.txt").read_text().splitlines()[:n]
    (root / "poses" / "00.txt").write_text("\n".join(lines) + "\n")
    return root


# ------------------------------------------------------------------ 1. PCD header vs data
PCD_LAYOUT = [("x", "f4", 1), ("y", "f4", 1), ("z", "f4", 1), ("intensity", "f4", 1)]


def write_pcd(path: Path, pts, inten, data: str, points: int | None = None) -> bytes:
    raw, _ = fuzz_inputs.pcd_bytes(pts, inten, PCD_LAYOUT, data, 1, points=points)
    path.write_bytes(raw)
    return raw


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_wrong_points_reads_every_point_and_says_so(kitti_extract, tmp_path, caplog, data):
    pts, inten = kitti_points(kitti_extract, every=8)
    path = tmp_path / "scan.pcd"
    write_pcd(path, pts, inten, data, points=1244)
    with caplog.at_level(logging.WARNING):
        got, got_i = read_pcd(path)
    np.testing.assert_array_equal(got, pts.astype(np.float64))
    np.testing.assert_array_equal(got_i, inten.astype(np.float64))
    lines = [r.getMessage() for r in caplog.records if "POINTS" in r.getMessage()]
    assert lines == [f"{path}: PCD header says POINTS 1244 but WIDTH x HEIGHT and the data hold {len(pts)} points; "
                     f"reading all {len(pts)}"]


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_data_shorter_than_width_x_height_is_an_input_error(kitti_extract, tmp_path, data):
    pts, inten = kitti_points(kitti_extract, every=8)
    path = tmp_path / "scan.pcd"
    raw = write_pcd(path, pts, inten, data)
    cut = len(raw) - 40 if data != "ascii" else raw.rindex(b"\n", 0, len(raw) - 1) + 1  # ascii: a whole line
    path.write_bytes(raw[:cut])
    with pytest.raises(InputError, match="truncated .pcd") as err:
        read_pcd(path)
    assert err.value.where == str(path) and "\n" not in str(err.value)


def test_pcd_data_longer_than_width_x_height_is_an_input_error(kitti_extract, tmp_path):
    pts, inten = kitti_points(kitti_extract, every=8)
    raw = write_pcd(tmp_path / "scan.pcd", pts, inten, "binary")
    (tmp_path / "scan.pcd").write_bytes(raw.replace(f"WIDTH {len(pts)}".encode(), b"WIDTH 1244"))
    with pytest.raises(InputError, match=rf"more than WIDTH x HEIGHT = 1244 points .*POINTS {len(pts)}"):
        read_pcd(tmp_path / "scan.pcd")


def test_cli_pcd_with_wrong_points_uses_the_whole_scan(kitti_extract, tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(3):
        pts, inten = kitti_points(kitti_extract, i)
        write_pcd(seq / f"{i:06d}.pcd", pts, inten, "binary_compressed", points=1244 if i == 1 else None)
    proc = run(seq, tmp_path / "r")
    assert proc.returncode == 0, proc.stderr
    n = len(kitti_points(kitti_extract, 1)[0])
    assert f"{seq / '000001.pcd'}: PCD header says POINTS 1244 but WIDTH x HEIGHT and the data hold {n} points" \
        in " ".join(proc.stderr.split())
    assert len(read_trajectory(tmp_path / "r" / "latest" / "trajectory_tum.txt")) == 3


# ------------------------------------------------------------------ 2. plausible coordinates
def test_cli_every_scan_far_away_stops_at_the_first_scan(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    for scan in scans:
        rec = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
        rec[:, :3] *= 1e29
        rec.tofile(scan)
    n = len(np.fromfile(scans[0], dtype=np.float32)) // 4
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert_one_line_error(proc, str(scans[0]), "only 0 valid points", f"{n} dropped beyond 1000 m",
                          "dataset.max_coordinate_m")


def test_cli_one_scan_far_away_keeps_the_frames_before_it(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 5)
    rec = np.fromfile(scans[3], dtype=np.float32).reshape(-1, 4)
    rec[:, :3] = 1e30
    rec.tofile(scans[3])
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert_one_line_error(proc, str(scans[3]), "only 0 valid points", "beyond 1000 m")
    latest = tmp_path / "r" / "latest"
    assert len(read_trajectory(latest / "trajectory_tum.txt")) == 3
    info = json.loads((latest / "run.json").read_text())
    assert info["frames_processed"] == 3 and info["failed_index"] == 3 and "beyond 1000 m" in info["error"]


def test_far_points_are_dropped_counted_and_logged_once(kitti_extract, tmp_path, caplog):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    for scan, k in zip(scans, (0, 25, 40)):
        rec = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
        rec[:k, 0] = 5000.0
        rec[k:k + 5, 1] = np.nan
        rec.tofile(scan)
    ds = open_dataset(tmp_path / "seq")
    with caplog.at_level(logging.WARNING):
        frames = list(ds)
    assert [f.extras["dropped_out_of_range"] for f in frames] == [0, 25, 40]
    assert [f.extras["dropped_nonfinite"] for f in frames] == [5, 5, 5]
    assert all(np.abs(f.points).max() <= 1000.0 and len(f.intensity) == len(f) for f in frames)
    far = [r.getMessage() for r in caplog.records if "beyond" in r.getMessage()]
    assert len(far) == 1 and far[0].startswith(f"{scans[1]}: dropped 25 points with a coordinate beyond 1000 m")
    wide = open_dataset(tmp_path / "seq", max_coordinate_m=1e4)
    assert wide.max_coordinate_m == 1e4 and wide[2].extras["dropped_out_of_range"] == 0


@pytest.mark.parametrize("value", [0, -100, float("nan"), float("inf")])
def test_max_coordinate_must_be_positive_and_finite(value):
    with pytest.raises(ValidationError, match="max_coordinate_m"):
        DatasetConfig(max_coordinate_m=value)


def test_cli_bad_max_coordinate_in_the_config(kitti_extract, tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("dataset: {max_coordinate_m: -5}\n")
    assert_one_line_error(run(kitti_extract, tmp_path / "r", "-c", cfg), str(cfg), "max_coordinate_m")


# ------------------------------------------------------------------ 3. timestamps
def test_checked_timestamps_error_and_repair(caplog):
    good = np.array([0.0, 0.1, 0.2])
    assert checked_timestamps(good, "t.txt") is good
    bad = np.array([0.0, 0.1, 0.1, 0.3, 0.25, 0.5])
    with pytest.raises(InputError) as err:
        checked_timestamps(bad, "t.txt")
    assert str(err.value) == ("t.txt: timestamps (s) must increase strictly: #2 = 0.1 is not after #1 = 0.1; "
                              "--fix-times (dataset.fix_times: true) repairs them")
    with caplog.at_level(logging.WARNING):
        fixed = checked_timestamps(bad, "t.txt", fix=True)
    np.testing.assert_allclose(fixed, [0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    assert "fix_times replaced 2 of 6 by the previous + the median interval 0.2" in caplog.text
    with pytest.raises(InputError, match="cannot repair: no positive interval"):
        checked_timestamps(np.zeros(3), "t.txt", fix=True)
    ns = np.array([10**18, 10**18 + 100_000_000, 10**18 + 100_000_000], dtype=np.int64)
    assert checked_timestamps(ns, "bag", fix=True, what="header stamps (ns)")[2] == 10**18 + 200_000_000


def test_cli_repeated_kitti_times_stop_the_run_or_are_repaired(kitti_extract, tmp_path):
    real = [float(t) for t in (kitti_extract / "sequences/00/times.txt").read_text().split()[:5]]
    times = [real[0], real[1], real[1], real[3], real[4]]
    root = make_kitti(kitti_extract, tmp_path / "kitti", 5, times)
    times_txt = root / "sequences/00/times.txt"
    proc = run(root, tmp_path / "r")
    assert_one_line_error(proc, str(times_txt), "must increase strictly", f"#2 = {real[1]!r} is not after #1",
                          "dataset.fix_times")
    assert not (tmp_path / "r" / "latest").exists()  # stopped before the first scan
    cfg = tmp_path / "fix.yaml"
    cfg.write_text("dataset: {fix_times: true}\n")
    proc = run(root, tmp_path / "r", "-c", cfg)
    assert proc.returncode == 0, proc.stderr
    assert "fix_times replaced 1 of 5" in " ".join(proc.stderr.split())
    latest = tmp_path / "r" / "latest"
    assert len(read_trajectory(latest / "trajectory_tum.txt")) == 5
    metrics = json.loads((latest / "metrics.json").read_text())
    assert metrics["n_poses_matched"] == 5  # with the repeated time only 3 of 5 matched, RPE 1.6 m
    proc = run(root, tmp_path / "r2", "--fix-times")  # the same, from the command line
    assert proc.returncode == 0 and "fix_times replaced 1 of 5" in " ".join(proc.stderr.split()), proc.stderr
    assert metrics["rpe"][0]["n_pairs"] == 4 and metrics["rpe"][0]["trans_m"]["rmse"] < 0.3


def test_folder_tum_poses_and_file_name_times(kitti_extract, tmp_path):
    pts, _ = kitti_points(kitti_extract)
    folder = tmp_path / "tum"
    folder.mkdir()
    for i in range(3):
        np.save(folder / f"{i}.npy", pts)
    poses = folder / "poses.txt"
    poses.write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.05 2 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"must increase strictly: #2 = 0\.05 is not after #1 = 0\.1") as err:
        open_dataset(folder)
    assert err.value.where == str(poses)
    np.testing.assert_allclose(open_dataset(folder, fix_times=True).timestamps, [0.0, 0.1, 0.2])
    stems = tmp_path / "stems"  # natural order puts 1.9 before 1.10, so the times go backwards
    stems.mkdir()
    for name in ("1.5", "1.9", "1.10"):
        np.save(stems / f"{name}.npy", pts)
    with pytest.raises(InputError, match=r"times from the file names \(s\) must increase strictly: #2 = 1\.1 is not "
                                         r"after #1 = 1\.9 \(1\.9\.npy, 1\.10\.npy\)") as err:
        open_dataset(stems)
    assert err.value.where == str(stems)


def test_simulated_and_argoverse2_times(kitti_extract, av2_log, tmp_path):
    root = make_kitti(kitti_extract, tmp_path / "sim", 3, [0.0, 0.1, 0.1])
    (root / "manifest.json").write_text('{"format": "flowslam-simulation"}')
    with pytest.raises(InputError, match=r"#2 = 0\.1 is not after #1 = 0\.1") as err:
        open_dataset(root)
    assert err.value.where == str(root / "sequences/00/times.txt")
    log = tmp_path / "av2"
    (log / "sensors" / "lidar").mkdir(parents=True)
    sweep = sorted((av2_log / "sensors" / "lidar").glob("*.feather"))[0]
    for name in (sweep.name, "0" + sweep.name, str(int(sweep.stem) + 100_000_000) + ".feather"):
        shutil.copy(sweep, log / "sensors/lidar" / name)  # the first two: the same nanosecond
    with pytest.raises(InputError, match=r"sweep times from the file names \(ns\) must increase strictly") as err:
        open_dataset(log)
    assert err.value.where == str(log / "sensors/lidar")
    ds = open_dataset(log, fix_times=True)
    assert list(np.diff(ds.timestamps_ns)) == [50_000_000] * 2 and len(ds[1]) > 0


def test_rosbag_repeated_header_stamps(kitti_extract, tmp_path):
    from flowslam.datasets.rosbag_writer import BagMessage, make_pointcloud2, typestore_for, write_bag

    ts = typestore_for("mcap")
    pts, inten = kitti_points(kitti_extract, every=16)
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": inten}
    stamps = [1_700_000_000_000_000_000 + d for d in (0, 100_000_000, 100_000_000, 300_000_000)]
    msgs = [BagMessage("/points", "sensor_msgs/msg/PointCloud2", 1_700_000_000_000_000_000 + k * 100_000_000,
                       make_pointcloud2(ts, s, cols)) for k, s in enumerate(stamps)]
    bag = write_bag(tmp_path / "bag", "mcap", msgs)
    with pytest.raises(InputError, match=r"header stamps \(ns\) must increase strictly: #2 = 1700000000100000000 "
                                         r"is not after #1") as err:
        open_dataset(bag)
    assert err.value.where == f"{bag} [/points]"
    ds = open_dataset(bag, fix_times=True)
    assert list(np.diff(ds.stamps_ns)) == [100_000_000] * 3
    assert ds[2].timestamp == pytest.approx(1_700_000_000.2) and ds[2].extras["stamp_ns"] == stamps[0] + 200_000_000
    ds.close()


# ------------------------------------------------------------------ 4. trajectory files
@pytest.mark.parametrize("text, problem", [
    ("", "holds no poses"),
    ("# only a comment\n", "holds no poses"),
    ("1 2 3 4 5 6 7\n", "7 columns"),
    ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", "rows of different lengths"),
    ("0 0 0 zero 0 0 0 1\n", "non-numeric"),
    ("0 0 0 nan 0 0 0 1\n", "NaN or inf"),
    ("0 0 0 1e999 0 0 0 1\n", "NaN or inf"),
    ("0 0 0 0 0 0 0 0\n", "zero quaternion"),
    ("0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 1\n", "#1 = 0.0 is not after #0 = 0.0"),
    ("1 0 0 0 0 0 0 1\n0.5 1 0 0 0 0 0 1\n", "#1 = 0.5 is not after #0 = 1.0"),
    ("1 0 0 0 0 1 0 0 0 0 1 0\n1.1 0 0 0 0 1 0 0 0 0 1 0\n", "pose on line 2 is not a rigid transform"),
    ("1 0 0 0 0 1 0 0 0 0 -1 0\n", "pose on line 1 is not a rigid transform"),
    (b"\xff\xfe\x00garbage", "cannot read poses file"),
], ids=["empty", "comments", "columns", "ragged", "text", "nan", "overflow", "zero-quat", "repeated", "backwards",
        "not-orthonormal", "reflection", "binary"])
def test_malformed_trajectory_files(tmp_path, text, problem):
    path = tmp_path / "poses.txt"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(InputError) as err:
        read_trajectory(path)
    assert err.value.where == str(path) and problem in err.value.problem and "\n" not in str(err.value)
