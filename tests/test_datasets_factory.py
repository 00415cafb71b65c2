"""open_dataset: format guessing on real data layouts, fmt override, errors, user formats, lazy imports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import flowslam.datasets as datasets
from flowslam.datasets import Dataset, Frame, available_formats, open_dataset, register_format
from flowslam.errors import InputError


@pytest.fixture(scope="module")
def small_scan(kitti_extract: Path) -> np.ndarray:
    return np.fromfile(kitti_extract / "sequences/00/velodyne/000000.bin", dtype=np.float32).reshape(-1, 4)[:2000]


@pytest.fixture(scope="module")
def bag_paths(small_scan, tmp_path_factory) -> dict[str, Path]:
    from flowslam.datasets.rosbag_writer import BagMessage, make_pointcloud2, typestore_for, write_bag

    root = tmp_path_factory.mktemp("factory_bags")
    out = {}
    for kind, name in (("ros1", "a.bag"), ("sqlite3", "b"), ("mcap", "c")):
        ts = typestore_for(kind)
        cols = {"x": small_scan[:, 0], "y": small_scan[:, 1], "z": small_scan[:, 2]}
        msg = make_pointcloud2(ts, 10**18, cols, [("x", "f4"), ("y", "f4"), ("z", "f4")])
        out[kind] = write_bag(root / name, kind, [BagMessage("/cloud", "sensor_msgs/msg/PointCloud2", 10**18, msg)])
    return out


def test_available_formats():
    assert available_formats() == ["rosbag", "simulated", "kitti", "argoverse2", "folder"]


def test_detects_real_layouts(kitti_extract: Path, av2_log: Path):
    for p in (kitti_extract, kitti_extract / "sequences" / "00", kitti_extract / "sequences/00/velodyne"):
        ds = open_dataset(p)
        assert ds.name == "kitti" and len(ds) == 16
    ds = open_dataset(kitti_extract, sequence="00")
    assert ds.has_gt_poses
    ds = open_dataset(av2_log)
    assert ds.name == "argoverse2" and len(ds) == 2


def test_detects_bags(bag_paths):
    for kind, path in bag_paths.items():
        ds = open_dataset(path)
        assert ds.name == "rosbag" and len(ds) == 1 and len(ds[0]) == 2000
        ds.close()
    db3 = next(bag_paths["sqlite3"].glob("*.db3"))
    ds = open_dataset(db3, topic="/cloud")
    assert ds.name == "rosbag"
    ds.close()


def test_detects_scan_folder_and_fmt_override(small_scan, kitti_extract: Path, tmp_path: Path):
    np.save(tmp_path / "0.npy", small_scan)
    np.save(tmp_path / "1.npy", small_scan)
    ds = open_dataset(tmp_path)
    assert ds.name == "folder" and len(ds) == 2
    # the KITTI velodyne folder read as a plain folder of .bin scans
    ds = open_dataset(kitti_extract / "sequences/00/velodyne", format="folder")
    assert ds.name == "folder" and len(ds) == 16 and ds.gt_poses is None


def test_errors(kitti_extract: Path, tmp_path: Path):
    with pytest.raises(InputError) as err:
        open_dataset(tmp_path / "missing")
    assert str(err.value) == f"{tmp_path / 'missing'}: does not exist"
    with pytest.raises(InputError, match=r"unknown format 'nuscenes' \(available: rosbag, simulated, kitti, argoverse2, folder\)"):
        open_dataset(kitti_extract, format="nuscenes")
    with pytest.raises(InputError, match=r"option\(s\) topic do not apply to the kitti format \(detected"):
        open_dataset(kitti_extract, topic="/points")
    notes = tmp_path / "notes.txt"
    notes.write_text("x")
    with pytest.raises(InputError, match=r"notes\.txt: cannot tell the dataset format; set dataset.format"):
        open_dataset(notes)
    with pytest.raises(InputError, match=r"no scans \(\.bin/\.pcd/\.ply/\.npy\) found"):
        open_dataset(tmp_path)


class _OneScan(Dataset):
    """A user reader: one synthetic ring scan from a '.ring' file."""

    name = "ring"

    def __init__(self, path, **options):
        super().__init__(path)
        self.options = options

    def __len__(self) -> int:
        return 1

    def _load(self, index: int) -> Frame:
        a = np.linspace(0, 2 * np.pi, 360, endpoint=False)
        return Frame(index, 0.0, np.column_stack([10 * np.cos(a), 10 * np.sin(a), np.zeros_like(a)]), source=str(self.path))


def test_register_format(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(datasets, "_USER", [])
    f = tmp_path / "scan.ring"
    f.write_text("")
    register_format("ring", _OneScan, lambda p: p.suffix == ".ring")
    assert available_formats()[0] == "ring"
    ds = open_dataset(f, topic="/x")
    assert isinstance(ds, _OneScan) and ds.options == {"topic": "/x"} and len(ds[0]) == 360
    # without a detector it is used only on request; re-registering replaces the entry
    register_format("ring", _OneScan)
    with pytest.raises(InputError, match="cannot tell the dataset format"):
        open_dataset(f)
    assert isinstance(open_dataset(f, format="ring"), _OneScan)
    assert available_formats().count("ring") == 1


def test_import_is_lazy():
    code = (
        "import sys, flowslam.datasets; "
        "heavy = [m for m in ('rosbags', 'pyarrow', 'open3d') if m in sys.modules]; "
        "print(heavy); sys.exit(1 if heavy else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
