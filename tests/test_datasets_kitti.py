"""KittiOdometry on the real KITTI 00 extract (frames 0-15) and on broken copies of it."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from flowslam import geometry
from flowslam.datasets.kitti import KittiOdometry, read_kitti_calib
from flowslam.errors import InputError

# Standard-looking KITTI camera projections (values as in the public devkit's calib files).
P_LINES = [
    "P0: 7.188560e+02 0.000000e+00 6.071928e+02 0.000000e+00 0.000000e+00 7.188560e+02 1.852157e+02 "
    "0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00",
    "P1: 7.188560e+02 0.000000e+00 6.071928e+02 -3.861448e+02 0.000000e+00 7.188560e+02 1.852157e+02 "
    "0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00",
    "P2: 7.188560e+02 0.000000e+00 6.071928e+02 4.538225e+01 0.000000e+00 7.188560e+02 1.852157e+02 "
    "-1.130887e-01 0.000000e+00 0.000000e+00 1.000000e+00 3.779761e-03",
    "P3: 7.188560e+02 0.000000e+00 6.071928e+02 -3.372877e+02 0.000000e+00 7.188560e+02 1.852157e+02 "
    "2.369057e+00 0.000000e+00 0.000000e+00 1.000000e+00 4.915215e-03",
]


@pytest.fixture(scope="module")
def kitti(kitti_extract: Path) -> KittiOdometry:
    return KittiOdometry(kitti_extract)


def make_copy(src_root: Path, dst_root: Path, *, n: int | None = None, calib_lines: list[str] | None = None,
              times: bool = True, poses_lines: int | None = None, seq: str = "00") -> Path:
    """A KITTI layout under dst_root with symlinked scans (first n), copied small text files."""
    src = src_root / "sequences" / "00"
    seq_dir = dst_root / "sequences" / seq
    (seq_dir / "velodyne").mkdir(parents=True)
    scans = sorted((src / "velodyne").glob("*.bin"))[:n]
    for f in scans:
        (seq_dir / "velodyne" / f.name).symlink_to(f)
    calib = (src / "calib.txt").read_text().splitlines()
    (seq_dir / "calib.txt").write_text("\n".join(calib_lines if calib_lines is not None else calib) + "\n")
    if times:
        (seq_dir / "times.txt").write_text("\n".join((src / "times.txt").read_text().splitlines()[: len(scans)]) + "\n")
    (dst_root / "poses").mkdir(exist_ok=True)
    pose_lines = (src_root / "poses" / "00.txt").read_text().splitlines()
    keep = len(scans) if poses_lines is None else poses_lines
    (dst_root / "poses" / f"{seq}.txt").write_text("\n".join(pose_lines[:keep]) + "\n")
    return dst_root


def test_real_extract_frames_and_points(kitti: KittiOdometry, kitti_extract: Path):
    assert len(kitti) == 16
    assert kitti.sequence == "00"
    counts = []
    for i, frame in enumerate(kitti):
        assert frame.index == i
        assert frame.points.dtype == np.float64 and frame.points.shape[1] == 3
        assert frame.point_times is None
        assert 0.0 <= frame.intensity.min() and frame.intensity.max() <= 1.0
        assert Path(frame.source).name == f"{i:06d}.bin"
        counts.append(len(frame))
    assert 120_000 <= min(counts) and max(counts) <= 125_000  # 120295 .. 124668 (README says ~121-125k)
    raw = np.fromfile(kitti_extract / "sequences/00/velodyne/000003.bin", dtype=np.float32).reshape(-1, 4)
    exact = KittiOdometry(kitti_extract, vertical_correction_deg=0)
    np.testing.assert_array_equal(exact[3].points, raw[:, :3].astype(np.float64))


def test_elevation_correction_equals_the_numpy_form(kitti_extract: Path):
    """The compiled correction gives the NumPy form's numbers bit for bit (a real scan, a
    point on the z axis, NaN rows), keeps each point's range and azimuth and raises its
    elevation by the angle."""
    from flowslam.datasets.kitti import correct_elevation

    raw = np.fromfile(kitti_extract / "sequences/00/velodyne/000003.bin", dtype=np.float32).reshape(-1, 4)
    pts = np.vstack([raw[:, :3].astype(np.float64), [[0.0, 0.0, 2.0], [np.nan, 1.0, 1.0], [1.0, 2.0, np.nan]]])
    angle = np.deg2rad(0.205)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    rho = np.hypot(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(rho > 0, (rho * np.cos(angle) - z * np.sin(angle)) / rho, 1.0)
    expected = np.column_stack([x * ratio, y * ratio, np.where(rho > 0, z * np.cos(angle) + rho * np.sin(angle), z)])
    got = correct_elevation(pts, angle)
    np.testing.assert_array_equal(got, expected)
    real = slice(0, len(raw))
    np.testing.assert_allclose(np.linalg.norm(got[real], axis=1), np.linalg.norm(pts[real], axis=1), rtol=1e-12)
    np.testing.assert_allclose(np.arctan2(got[real, 1], got[real, 0]), np.arctan2(pts[real, 1], pts[real, 0]), atol=1e-12)
    rises = np.arctan2(got[real, 2], np.hypot(got[real, 0], got[real, 1])) - np.arctan2(z[real], rho[real])
    np.testing.assert_allclose(rises, angle, atol=1e-9)


def test_real_extract_times_and_gt(kitti: KittiOdometry, kitti_extract: Path):
    times = np.loadtxt(kitti_extract / "sequences/00/times.txt")
    np.testing.assert_array_equal(kitti.timestamps, times)
    assert kitti[5].timestamp == pytest.approx(times[5])
    assert kitti.gt_poses.shape == (16, 4, 4)
    np.testing.assert_allclose(kitti.gt_poses[0], np.eye(4), atol=1e-6)
    steps = geometry.translation_norm(geometry.relative(kitti.gt_poses[:-1], kitti.gt_poses[1:]))
    np.testing.assert_allclose(steps, 0.86, atol=0.01)
    # the car drives forward: along the Velodyne x axis
    assert kitti.gt_poses[-1][0, 3] > 12.0
    assert all(geometry.is_se3(T, tol=1e-5) for T in kitti.gt_poses)
    np.testing.assert_array_equal(kitti[7].gt_pose, kitti.gt_poses[7])


def test_sequence_folder_and_velodyne_folder(kitti: KittiOdometry, kitti_extract: Path):
    for p in (kitti_extract / "sequences/00", kitti_extract / "sequences/00/velodyne"):
        ds = KittiOdometry(p)
        assert len(ds) == 16 and ds.sequence == "00"
        np.testing.assert_array_equal(ds.gt_poses, kitti.gt_poses)
    assert len(KittiOdometry(kitti_extract, sequence=0)) == 16


def test_calib_with_projection_matrices_gives_same_result(kitti: KittiOdometry, kitti_extract: Path, tmp_path: Path):
    tr = (kitti_extract / "sequences/00/calib.txt").read_text().splitlines()[0]
    root = make_copy(kitti_extract, tmp_path, calib_lines=P_LINES + [tr])
    ds = KittiOdometry(root)
    assert sorted(ds.calib) == ["P0", "P1", "P2", "P3", "Tr"]
    np.testing.assert_array_equal(ds.gt_poses, kitti.gt_poses)
    np.testing.assert_array_equal(ds[4].points, kitti[4].points)
    np.testing.assert_array_equal(ds.timestamps, kitti.timestamps)


def test_several_sequences_need_a_choice(kitti_extract: Path, tmp_path: Path):
    make_copy(kitti_extract, tmp_path, n=3)
    make_copy(kitti_extract, tmp_path, n=2, seq="07")
    with pytest.raises(InputError, match=r"several sequences \(00, 07\); pick one with sequence="):
        KittiOdometry(tmp_path)
    assert len(KittiOdometry(tmp_path, sequence="07")) == 2
    assert len(KittiOdometry(tmp_path, sequence=0)) == 3
    with pytest.raises(InputError, match=r"no sequence '05' \(available: 00, 07\)"):
        KittiOdometry(tmp_path, sequence=5)


def test_missing_times_defaults_to_10hz(kitti_extract: Path, tmp_path: Path, caplog):
    root = make_copy(kitti_extract, tmp_path, n=4, times=False)
    with caplog.at_level(logging.WARNING):
        ds = KittiOdometry(root)
    assert "no times.txt" in caplog.text
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2, 0.3])


def test_truncated_bin_fails_only_at_that_frame(kitti_extract: Path, tmp_path: Path):
    root = make_copy(kitti_extract, tmp_path, n=3)
    last = root / "sequences/00/velodyne/000002.bin"
    data = last.read_bytes()
    last.unlink()
    last.write_bytes(data[:1000])  # 1000 is not a multiple of 16
    ds = KittiOdometry(root)
    assert len(ds[0]) > 100_000 and len(ds[1]) > 100_000
    with pytest.raises(InputError) as err:
        ds[2]
    assert err.value.where == str(last)
    assert "1000 bytes is not a multiple of 16" in str(err.value)


def test_nan_points_dropped_with_count(kitti_extract: Path, tmp_path: Path, caplog):
    root = make_copy(kitti_extract, tmp_path, n=1)
    f = root / "sequences/00/velodyne/000000.bin"
    rec = np.fromfile(f, dtype=np.float32).reshape(-1, 4).copy()
    rec[[3, 10, 20], 0] = np.nan
    rec[[30, 40], 2] = np.inf
    f.unlink()
    rec.tofile(f)
    with caplog.at_level(logging.WARNING):
        frame = KittiOdometry(root)[0]
    assert len(frame) == len(rec) - 5 and len(frame.intensity) == len(rec) - 5
    assert frame.extras["dropped_nonfinite"] == 5
    assert "dropped 5 points with NaN/inf" in caplog.text and "000000.bin" in caplog.text


def test_too_few_points(kitti_extract: Path, tmp_path: Path):
    root = make_copy(kitti_extract, tmp_path, n=1)
    f = root / "sequences/00/velodyne/000000.bin"
    rec = np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:150].copy()
    rec[:80, :3] = np.nan
    f.unlink()
    rec.tofile(f)
    with pytest.raises(InputError, match=r"000000\.bin: only 70 valid points in this scan"):
        KittiOdometry(root)[0]


def test_wrong_length_poses(kitti_extract: Path, tmp_path: Path):
    root = make_copy(kitti_extract, tmp_path, n=4, poses_lines=6)
    with pytest.raises(InputError) as err:
        KittiOdometry(root)
    assert err.value.where == str(root / "poses" / "00.txt")
    assert "6 poses but there are 4 scans" in err.value.problem


def test_unreadable_poses(kitti_extract: Path, tmp_path: Path):
    root = make_copy(kitti_extract, tmp_path, n=2)
    (root / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\nthis is not a pose line at all ok?\n")
    with pytest.raises(InputError) as err:
        KittiOdometry(root)
    assert err.value.where == str(root / "poses" / "00.txt")
    assert "rows of different lengths" in err.value.problem


def test_empty_velodyne_folder(tmp_path: Path):
    velo = tmp_path / "sequences" / "00" / "velodyne"
    velo.mkdir(parents=True)
    with pytest.raises(InputError) as err:
        KittiOdometry(tmp_path)
    assert err.value.where == str(velo) and "no .bin scans found" in err.value.problem


def test_bad_calib(kitti_extract: Path, tmp_path: Path):
    root = make_copy(kitti_extract, tmp_path, n=2, calib_lines=P_LINES)  # no Tr
    with pytest.raises(InputError, match=r"calib\.txt: no 'Tr:'"):
        KittiOdometry(root)
    (root / "sequences/00/calib.txt").write_text("Tr: 1 0 0\n")
    with pytest.raises(InputError, match=r"has 3 numbers, expected 12"):
        read_kitti_calib(root / "sequences/00/calib.txt")
    (root / "sequences/00/calib.txt").unlink()
    with pytest.raises(InputError, match=r"calib\.txt: missing; its Tr is needed"):
        KittiOdometry(root)


def test_missing_path_and_non_kitti_folder(tmp_path: Path):
    with pytest.raises(InputError, match="does not exist"):
        KittiOdometry(tmp_path / "nope")
    with pytest.raises(InputError, match="not a KITTI odometry folder"):
        KittiOdometry(tmp_path)


def test_vertical_correction_matches_kiss_icp(kitti_extract):
    """Our elevation correction equals the one KISS-ICP applies to KITTI scans (real oracle)."""
    from kiss_icp.pybind import kiss_icp_pybind

    raw = KittiOdometry(kitti_extract, vertical_correction_deg=0)[3].points
    ours = KittiOdometry(kitti_extract)[3].points
    theirs = np.asarray(kiss_icp_pybind._correct_kitti_scan(kiss_icp_pybind._Vector3dVector(raw)))
    np.testing.assert_allclose(ours, theirs, atol=1e-9)
    assert np.abs(ours - raw).max() > 0.05  # it does move far points
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), np.linalg.norm(raw, axis=1), atol=1e-9)
