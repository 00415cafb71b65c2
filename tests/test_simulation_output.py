"""The written sequence: KITTI layout that other tools read unchanged (KISS-ICP's own
KITTI loader), the manifest, the preview PNG, and the cached demo sequence."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("out") / "seq"
    manifest = simulate(out, preset="dt", frames=4, seed=2, sensor="vlp16", columns=360, workers=1)
    return out, manifest


def test_kitti_layout(small):
    out, manifest = small
    seq = out / "sequences" / "00"
    scans = sorted((seq / "velodyne").glob("*.bin"))
    assert [p.name for p in scans] == [f"{i:06d}.bin" for i in range(4)]
    assert sorted(p.name for p in (seq / "gt").iterdir()) == [f"{i:06d}.npz" for i in range(4)]
    calib = dict(line.split(":", 1) for line in (seq / "calib.txt").read_text().splitlines())
    assert np.allclose(np.array(calib["Tr"].split(), float).reshape(3, 4), np.eye(4)[:3])
    times = np.loadtxt(seq / "times.txt")
    assert np.allclose(times, [0.0, 0.1, 0.2, 0.3])
    poses = np.loadtxt(out / "poses" / "00.txt").reshape(-1, 3, 4)
    assert len(poses) == 4 and np.allclose(poses[0], np.eye(4)[:3])
    xyzi = np.fromfile(scans[0], dtype="<f4").reshape(-1, 4)
    gt = np.load(seq / "gt" / "000000.npz")
    assert len(xyzi) == len(gt["flow"]) == len(gt["class"]) == len(gt["instance"]) == len(gt["dynamic"])
    assert gt["flow"].dtype == np.float32 and gt["class"].dtype == np.uint8
    assert np.all((xyzi[:, 3] >= 0) & (xyzi[:, 3] <= 1))
    assert manifest["stats"]["points_per_frame"]["min"] > 1000


def test_manifest(small):
    out, manifest = small
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk["format"] == "flowslam-simulation"
    assert on_disk["preset"] == "dt" and on_disk["seed"] == 2 and on_disk["frames"] == 4
    assert on_disk["sensor"]["name"] == "vlp16" and on_disk["sensor"]["columns"] == 360
    assert on_disk["sensor"]["beams"] == 16 and on_disk["distortion"] is False
    assert set(on_disk["generator"]) >= {"simulator", "flowslam", "numpy", "open3d"}
    assert on_disk["classes"]["12"]["name"] == "pedestrian"
    assert len(on_disk["stats"]["dynamic_points"]) == 4
    assert on_disk["actors"]["by_role"]["convoy"] == 1
    assert "timing_s" not in on_disk and "timing_s" in manifest  # the file stays reproducible


def test_kiss_icp_reads_it_unchanged(small):
    from kiss_icp.datasets.kitti import KITTIOdometryDataset

    out, _ = small
    ds = KITTIOdometryDataset(str(out), sequence="00")
    assert len(ds) == 4
    points, _ = ds[1]
    assert points.shape[1] == 3 and len(points) > 1000
    assert np.allclose(ds.gt_poses[0], np.eye(4))
    assert ds.gt_poses[3][0, 3] > 0.5  # the ego drives forward (x)


def test_preview_png(small, tmp_path):
    from PIL import Image

    from flowslam.simulation import write_preview

    out, _ = small
    path = write_preview(out, tmp_path / "preview.png")
    assert path.stat().st_size < 300_000
    with Image.open(path) as im:
        assert im.size[0] > 800 and im.size[1] > 400
        assert len(im.getcolors(maxcolors=256) or []) > 8  # not a blank image


def test_demo_sequence_is_cached(tmp_path, monkeypatch):
    from flowslam.simulation import demo

    monkeypatch.setattr(demo, "DEMO_SETTINGS", {"preset": "demo", "seed": 0, "frames": 3, "sensor": "vlp16",
                                                "columns": 90, "workers": 1})
    monkeypatch.setenv("FLOWSLAM_CACHE", str(tmp_path / "cache"))
    calls = []
    first = demo.ensure_demo_sequence(progress=lambda done, total: calls.append(done))
    assert first.parent == tmp_path / "cache" and first.name.startswith("demo-")
    assert (first / "manifest.json").is_file() and calls == [1, 2, 3]
    stamp = (first / "manifest.json").stat().st_mtime_ns
    again = demo.ensure_demo_sequence(progress=lambda done, total: calls.append(done))
    assert again == first and calls == [1, 2, 3]
    assert (first / "manifest.json").stat().st_mtime_ns == stamp
    other = demo.ensure_demo_sequence(tmp_path / "elsewhere")
    assert other.parent == tmp_path / "elsewhere" and other.name == first.name
    assert not [p for p in (tmp_path / "cache").iterdir() if p.name.startswith(".")]  # no temporary left
