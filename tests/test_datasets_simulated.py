"""The reader of simulated sequences: detected by its manifest, no KITTI elevation
correction, ground truth through the common Frame interface."""

from __future__ import annotations

import numpy as np
import pytest

from flowslam.errors import InputError


@pytest.fixture(scope="module", params=[False, True], ids=["instantaneous", "distorted"])
def sim(request, tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "seq"
    simulate(out, preset="dt", frames=3, seed=4, sensor="vlp16", columns=360, distortion=request.param,
             workers=1)
    return out, request.param


def test_detected_from_root_sequence_and_velodyne_folders(sim):
    from flowslam.datasets import available_formats, open_dataset
    from flowslam.datasets.simulated import SimulatedSequence

    out, _ = sim
    assert available_formats().index("simulated") < available_formats().index("kitti")
    for path in (out, out / "sequences" / "00", out / "sequences" / "00" / "velodyne"):
        ds = open_dataset(path)
        assert isinstance(ds, SimulatedSequence) and len(ds) == 3
    assert "simulated (dt, seed 4, vlp16" in open_dataset(out).describe()


def test_no_kitti_elevation_correction(sim):
    from flowslam.datasets import open_dataset
    from flowslam.datasets.scan_files import read_kitti_bin

    out, _ = sim
    ds = open_dataset(out)
    raw, inten = read_kitti_bin(out / "sequences/00/velodyne/000001.bin")
    f = ds[1]
    assert np.array_equal(f.points, raw) and np.array_equal(f.intensity, inten)
    with pytest.raises(InputError, match="vertical_correction_deg do not apply"):
        open_dataset(out, kitti_vertical_correction_deg=0.205)
    kitti = open_dataset(out, format="kitti")  # the plain KITTI reader would correct it
    assert not np.allclose(kitti[1].points, raw)


def test_frame_ground_truth(sim):
    from flowslam.datasets import open_dataset

    out, distortion = sim
    ds = open_dataset(out)
    poses = np.loadtxt(out / "poses/00.txt").reshape(-1, 3, 4)
    assert np.allclose(ds.gt_poses[:, :3], poses)
    assert np.allclose(ds.timestamps, [0.0, 0.1, 0.2])
    assert np.allclose(ds.pose_at(ds.timestamps), ds.gt_poses, atol=1e-9)
    assert np.allclose(ds.pose_at(0.1), ds.gt_poses[1], atol=1e-9)
    between = ds.pose_at(0.05)
    assert 0 < between[0, 3] - ds.gt_poses[0][0, 3] < ds.gt_poses[1][0, 3] - ds.gt_poses[0][0, 3]
    f = ds[0]
    n = len(f.points)
    assert f.gt_flow.shape == (n, 3) and f.gt_dynamic.shape == (n,)
    assert f.gt_class.shape == (n,) and f.gt_instance.shape == (n,)
    assert f.extras["flow_compensated"].shape == (n, 3)
    assert set(np.unique(f.gt_class)) <= set(ds.class_names)
    assert (f.gt_instance == -1).any() and f.gt_dynamic.any()
    assert np.array_equal(f.gt_dynamic, np.linalg.norm(f.extras["flow_compensated"], axis=1) > 0.05)
    if distortion:
        assert f.point_times is not None and 0.0 <= f.point_times.min() and f.point_times.max() < 0.1
        assert np.allclose(f.point_times, f.extras["column"] * 0.1 / 360, atol=1e-6)
    else:
        assert f.point_times is None


def test_deskewed_points(sim):
    from flowslam.datasets import open_dataset

    out, distortion = sim
    ds = open_dataset(out)
    f = ds[1]
    d = ds.deskewed(1)
    if not distortion:
        assert np.array_equal(d, f.points)
        return
    # a static point's world position, via its own firing pose or via the frame pose, agrees
    scene = ds.scene
    static = f.gt_instance < 100_000
    T_first = scene.T_town_first
    T_frame = np.linalg.inv(T_first) @ scene.T_town_sensor(np.array([ds.timestamps[1]]))[0]
    assert np.allclose(T_frame, ds.gt_poses[1], atol=1e-9)
    A = scene.T_town_sensor(ds.timestamps[1] + f.point_times)
    world_own = np.einsum("nij,nj->ni", A[:, :3, :3], f.points) + A[:, :3, 3]
    world_frame = d @ scene.T_town_sensor(np.array([ds.timestamps[1]]))[0][:3, :3].T + \
        scene.T_town_sensor(np.array([ds.timestamps[1]]))[0][:3, 3]
    assert np.abs(world_own - world_frame)[static].max() < 1e-6
    assert np.abs(d - f.points).max() > 0.01  # the ego moved during the sweep


def test_missing_ground_truth_file(sim, tmp_path):
    import shutil

    from flowslam.datasets import open_dataset

    out, _ = sim
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "sequences/00/gt/000002.npz").unlink()
    ds = open_dataset(copy)
    with pytest.raises(InputError, match="ground-truth file missing"):
        ds[2]
    (copy / "manifest.json").write_text("{}")
    from flowslam.datasets.simulated import is_simulated

    assert not is_simulated(copy)  # not a simulator manifest: plain KITTI then
