"""ScanFolder: .bin/.npy/.pcd/.ply scans written from real KITTI points, poses and timestamps."""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
import pytest

from flowslam import geometry
from flowslam.datasets.folder import ScanFolder
from flowslam.datasets.pcd import read_pcd
from flowslam.datasets.scan_files import read_kitti_bin, read_scan
from flowslam.errors import InputError
from flowslam.trajectory import Trajectory, write_kitti, write_tum


@pytest.fixture(scope="module")
def real_scans(kitti_extract: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Three real KITTI scans as float32 (points (N,3), intensity (N,))."""
    out = []
    for i in range(3):
        rec = np.fromfile(kitti_extract / f"sequences/00/velodyne/{i:06d}.bin", dtype=np.float32).reshape(-1, 4)
        out.append((rec[:, :3].copy(), rec[:, 3].copy()))
    return out


def write_pcd(path: Path, columns: list[tuple[str, np.ndarray, str]], data: str = "binary") -> None:
    """Write a PCD v0.7 file; ``columns`` = (name, (N,) or (N,count) array, numpy code)."""
    n = len(columns[0][1])
    counts = [1 if a.ndim == 1 else a.shape[1] for _, a, _ in columns]
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(name for name, _, _ in columns),
        "SIZE " + " ".join(str(np.dtype(c).itemsize) for _, _, c in columns),
        "TYPE " + " ".join({"f": "F", "i": "I", "u": "U"}[np.dtype(c).kind] for _, _, c in columns),
        "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n}",
        f"DATA {data}",
    ]
    body: bytes
    if data == "binary":
        dt = np.dtype([(name if name != "_" else f"_{k}", "<" + c, (cnt,) if cnt > 1 else ())
                       for k, ((name, _, c), cnt) in enumerate(zip(columns, counts))])
        rec = np.zeros(n, dtype=dt)
        for k, (name, arr, _) in enumerate(columns):
            rec[dt.names[k]] = arr
        body = rec.tobytes()
    else:
        table = np.column_stack([a.reshape(n, -1).astype(np.float64) for _, a, _ in columns])
        buf = io.BytesIO()
        np.savetxt(buf, table, fmt="%.9g")
        body = buf.getvalue()
    path.write_bytes(("\n".join(header) + "\n").encode() + body)


def test_bin_npy_round_trip(real_scans, kitti_extract: Path, tmp_path: Path):
    pts, inten = real_scans[0]
    (tmp_path / "a.bin").symlink_to(kitti_extract / "sequences/00/velodyne/000000.bin")
    np.save(tmp_path / "b.npy", np.column_stack([pts, inten]).astype(np.float64))
    np.save(tmp_path / "c.npy", pts)  # (N,3) float32, no intensity
    struct = np.zeros(len(pts), dtype=[("intensity", "f4"), ("x", "f8"), ("y", "f8"), ("z", "f8")])
    for k, name in enumerate("xyz"):
        struct[name] = pts[:, k]
    struct["intensity"] = inten
    np.save(tmp_path / "d.npy", struct)
    ds = ScanFolder(tmp_path)
    assert [p.name for p in ds.scan_files] == ["a.bin", "b.npy", "c.npy", "d.npy"]
    for i, frame in enumerate(ds):
        np.testing.assert_array_equal(frame.points, pts.astype(np.float64))
        if i == 2:
            assert frame.intensity is None
        else:
            np.testing.assert_array_equal(frame.intensity, inten.astype(np.float64))


@pytest.mark.parametrize("data", ["ascii", "binary"])
def test_pcd_round_trip(real_scans, tmp_path: Path, data: str):
    pts, inten = real_scans[1]
    write_pcd(tmp_path / "plain.pcd", [("x", pts[:, 0], "f4"), ("y", pts[:, 1], "f4"), ("z", pts[:, 2], "f4"),
                                       ("intensity", inten, "f4")], data)
    # non-trivial layout: other field order, padding, float64 coordinates, a count-3 field, uint16 ring
    ring = (np.arange(len(pts)) % 64).astype(np.uint16)
    normals = np.tile(np.array([0, 0, 1], np.float32), (len(pts), 1))
    write_pcd(tmp_path / "odd.pcd", [("ring", ring, "u2"), ("_", np.zeros(len(pts), np.uint16), "u2"),
                                     ("intensity", inten, "f4"), ("normal", normals, "f4"),
                                     ("z", pts[:, 2], "f8"), ("x", pts[:, 0], "f8"), ("y", pts[:, 1], "f8")], data)
    ds = ScanFolder(tmp_path)
    assert [p.name for p in ds.scan_files] == ["odd.pcd", "plain.pcd"]
    atol = 1e-6 if data == "ascii" else 0.0
    for frame in ds:
        np.testing.assert_allclose(frame.points, pts.astype(np.float64), rtol=0, atol=atol)
        np.testing.assert_allclose(frame.intensity, inten.astype(np.float64), rtol=0, atol=atol)


def test_pcd_compressed_and_ply_via_open3d(real_scans, tmp_path: Path):
    o3d = pytest.importorskip("open3d")
    pts, inten = real_scans[2]
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(pts)
    pc.point.intensity = o3d.core.Tensor(inten.reshape(-1, 1))
    o3d.t.io.write_point_cloud(str(tmp_path / "s1.ply"), pc)
    o3d.t.io.write_point_cloud(str(tmp_path / "s2.pcd"), pc, compressed=True)
    np.testing.assert_array_equal(read_pcd(tmp_path / "s2.pcd")[0], pts.astype(np.float64))  # our LZF decoder
    for frame in ScanFolder(tmp_path):
        np.testing.assert_array_equal(frame.points, pts.astype(np.float64))
        np.testing.assert_array_equal(frame.intensity, inten.astype(np.float64))


def test_natural_order_and_timestamp_rules(real_scans, tmp_path: Path, caplog):
    pts, _ = real_scans[0]
    sub = pts[:500]
    for name in ("scan_10.npy", "scan_2.npy", "scan_1.npy"):
        np.save(tmp_path / name, sub)
    with caplog.at_level(logging.WARNING):
        ds = ScanFolder(tmp_path)
    assert [p.name for p in ds.scan_files] == ["scan_1.npy", "scan_2.npy", "scan_10.npy"]
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2])
    assert "no timestamps found" in caplog.text

    ns = tmp_path / "ns"
    ns.mkdir()
    for stamp in (1_700_000_000_250_000_000, 1_700_000_000_150_000_000):
        np.save(ns / f"{stamp}.npy", sub)
    np.testing.assert_allclose(ScanFolder(ns).timestamps, [1_700_000_000.15, 1_700_000_000.25], rtol=0, atol=1e-6)

    secs = tmp_path / "secs"
    secs.mkdir()
    for stamp in ("12.5", "12.6", "12.75"):
        np.save(secs / f"{stamp}.npy", sub)
    np.testing.assert_allclose(ScanFolder(secs).timestamps, [12.5, 12.6, 12.75])

    idx = tmp_path / "idx"
    idx.mkdir()
    for k in range(3):
        np.save(idx / f"{k:06d}.npy", sub)
    np.testing.assert_allclose(ScanFolder(idx).timestamps, [0.0, 0.1, 0.2])  # indices, not times
    (idx / "times.txt").write_text("5.0\n5.1\n5.25\n")
    np.testing.assert_allclose(ScanFolder(idx).timestamps, [5.0, 5.1, 5.25])
    (idx / "times.txt").write_text("5.0\n5.1\n")
    with pytest.raises(InputError, match=r"times\.txt: has 2 timestamps but there are 3 scans"):
        ScanFolder(idx)


@pytest.fixture()
def folder_with_gt(real_scans, kitti_extract: Path, tmp_path: Path) -> tuple[Path, np.ndarray]:
    for i in range(3):
        (tmp_path / f"{i:06d}.bin").symlink_to(kitti_extract / f"sequences/00/velodyne/{i:06d}.bin")
    poses = np.stack([geometry.from_euler("z", 0.01 * i, [0.86 * i, 0.02 * i, 0.0]) for i in range(3)])
    return tmp_path, poses


def test_tum_poses_discovered(folder_with_gt):
    folder, poses = folder_with_gt
    write_tum(folder / "poses_tum.txt", Trajectory(poses, np.array([100.0, 100.1, 100.2])))
    ds = ScanFolder(folder)
    assert ds.poses_path.name == "poses_tum.txt"
    np.testing.assert_allclose(ds.gt_poses, poses, atol=1e-8)
    np.testing.assert_allclose(ds.timestamps, [100.0, 100.1, 100.2])
    np.testing.assert_allclose(ds[2].gt_pose, poses[2], atol=1e-8)


def test_kitti_poses_argument(folder_with_gt, tmp_path_factory):
    folder, poses = folder_with_gt
    elsewhere = tmp_path_factory.mktemp("gt") / "my_gt.txt"
    write_kitti(elsewhere, poses)
    ds = ScanFolder(folder, poses=elsewhere)
    np.testing.assert_allclose(ds.gt_poses, poses, atol=1e-8)
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2])


def test_wrong_length_and_unreadable_poses(folder_with_gt):
    folder, poses = folder_with_gt
    write_kitti(folder / "poses.txt", poses[:2])
    with pytest.raises(InputError) as err:
        ScanFolder(folder)
    assert err.value.where == str(folder / "poses.txt")
    assert "has 2 poses but the folder has 3 scans" in err.value.problem
    (folder / "poses.txt").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputError) as err:
        ScanFolder(folder)
    assert err.value.where == str(folder / "poses.txt")
    assert "cannot read poses file" in err.value.problem
    with pytest.raises(InputError, match="does not exist"):
        ScanFolder(folder, poses=folder / "missing.txt")


def test_empty_folder(tmp_path: Path):
    with pytest.raises(InputError) as err:
        ScanFolder(tmp_path)
    assert str(err.value) == f"{tmp_path}: no scans (.bin/.pcd/.ply/.npy) found"
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match=r"no scans \(\.bin/\.pcd/\.ply/\.npy\) found"):
        ScanFolder(tmp_path)
    with pytest.raises(InputError, match="does not exist"):
        ScanFolder(tmp_path / "nope")


def test_nonfinite_dropped_and_too_few_points(real_scans, tmp_path: Path, caplog):
    pts, inten = real_scans[0]
    arr = np.column_stack([pts[:1000], inten[:1000]]).astype(np.float64)
    arr[:7, 1] = np.nan
    arr[7:9, 0] = -np.inf
    np.save(tmp_path / "a.npy", arr)
    np.save(tmp_path / "b.npy", arr[:99])
    ds = ScanFolder(tmp_path)
    with caplog.at_level(logging.WARNING):
        frame = ds[0]
    assert len(frame) == 991 and len(frame.intensity) == 991
    assert f"{tmp_path / 'a.npy'}: dropped 9 points with NaN/inf coordinates" in caplog.text
    with pytest.raises(InputError) as err:
        ds[1]
    assert err.value.where == str(tmp_path / "b.npy")
    assert "only 90 valid points" in err.value.problem


def test_bad_scan_files(real_scans, tmp_path: Path):
    pts, inten = real_scans[0]
    (tmp_path / "t.bin").write_bytes(np.column_stack([pts[:200], inten[:200]]).astype(np.float32).tobytes()[:-6])
    with pytest.raises(InputError, match=r"t\.bin: size 3194 bytes is not a multiple of 16"):
        read_scan(tmp_path / "t.bin")
    write_pcd(tmp_path / "t.pcd", [("x", pts[:, 0], "f4"), ("y", pts[:, 1], "f4"), ("z", pts[:, 2], "f4")])
    (tmp_path / "t.pcd").write_bytes((tmp_path / "t.pcd").read_bytes()[:-100])
    with pytest.raises(InputError, match=r"t\.pcd: binary data has .* \(truncated \.pcd\?\)"):
        read_scan(tmp_path / "t.pcd")
    write_pcd(tmp_path / "noz.pcd", [("x", pts[:, 0], "f4"), ("y", pts[:, 1], "f4")], "ascii")
    with pytest.raises(InputError, match=r"noz\.pcd: PCD has no field\(s\) \['z'\]"):
        read_scan(tmp_path / "noz.pcd")
    np.save(tmp_path / "flat.npy", pts[:, 0])
    with pytest.raises(InputError, match=r"flat\.npy: array has shape \(\d+,\)"):
        read_scan(tmp_path / "flat.npy")
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    with pytest.raises(InputError, match=r"junk\.npy: not a readable \.npy array"):
        read_scan(tmp_path / "junk.npy")
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(InputError, match=r"junk\.ply: not a PLY file"):
        read_scan(tmp_path / "junk.ply")


def test_read_kitti_bin_matches_numpy(kitti_extract: Path):
    f = kitti_extract / "sequences/00/velodyne/000009.bin"
    pts, inten = read_kitti_bin(f)
    raw = np.fromfile(f, dtype=np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(pts, raw[:, :3])
    np.testing.assert_array_equal(inten, raw[:, 3])
