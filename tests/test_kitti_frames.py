"""Trajectory files in KITTI's convention (camera 0, as ``poses/XX.txt``) and the LiDAR frame.

For KITTI input ``trajectory_kitti.txt`` must compare with the official poses in any tool:
``flowslam eval trajectory_kitti.txt poses/00.txt`` gives the run's own ``metrics.json``.
"""

import json

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config import load_config
from flowslam.datasets.kitti import KittiOdometry, cam0_poses_to_velo, velo_poses_to_cam0
from flowslam.pipeline import RunResult
from flowslam.results import write_results
from flowslam.trajectory import read_trajectory

from cli_helpers import flowslam


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([geometry.exp_se3(rng.normal(scale=[0.1, 0.1, 0.1, 2, 2, 2])) for _ in range(n)])


def test_conversions_undo_each_other_and_keep_the_identity():
    Tr = geometry.exp_se3(np.array([1.2, -0.3, 1.5, -0.01, -0.05, -0.29]))
    poses = _random_poses(5)
    np.testing.assert_allclose(cam0_poses_to_velo(velo_poses_to_cam0(poses, Tr), Tr), poses, atol=1e-12)
    np.testing.assert_allclose(velo_poses_to_cam0(np.eye(4)[None], Tr)[0], np.eye(4), atol=1e-15)
    # a point seen by the LiDAR at pose k: same world point through either chain
    p_velo_k = np.array([3.0, -1.0, 0.5, 1.0])
    cam = velo_poses_to_cam0(poses, Tr)
    for T_velo, T_cam in zip(poses, cam):
        np.testing.assert_allclose(Tr @ T_velo @ p_velo_k, T_cam @ (Tr @ p_velo_k), atol=1e-12)


def _result(poses: np.ndarray) -> RunResult:
    n = len(poses)
    odometry = [geometry.relative(poses[k - 1], poses[k]) for k in range(1, n)]
    return RunResult(list(range(n)), list(0.1 * np.arange(n)), [0.01] * n, poses, odometry)


def test_without_calibration_the_kitti_file_is_the_sensor_frame(tmp_path):
    poses = _random_poses(4, seed=1)
    poses = geometry.inv(poses[0]) @ poses  # world = first scan
    cfg = load_config()
    cfg.output.plot = False
    write_results(tmp_path, _result(poses), cfg, gt=None, metrics=None)
    kitti = read_trajectory(tmp_path / "trajectory_kitti.txt").poses
    np.testing.assert_allclose(kitti, read_trajectory(tmp_path / "trajectory_kitti_lidar.txt").poses, atol=0)
    np.testing.assert_allclose(kitti, poses, atol=1e-8)


def test_with_calibration_only_the_kitti_files_change(tmp_path):
    poses = _random_poses(4, seed=2)
    poses = geometry.inv(poses[0]) @ poses
    Tr = geometry.exp_se3(np.array([1.2, -0.3, 1.5, -0.01, -0.05, -0.29]))
    cfg = load_config()
    cfg.output.plot = False
    gt = _result(poses[::-1].copy()).trajectory
    write_results(tmp_path, _result(poses), cfg, gt=gt, metrics=None, T_cam0_sensor=Tr)
    np.testing.assert_allclose(read_trajectory(tmp_path / "trajectory_tum.txt").poses, poses, atol=1e-8)
    np.testing.assert_allclose(read_trajectory(tmp_path / "trajectory_kitti_lidar.txt").poses, poses, atol=1e-8)
    np.testing.assert_allclose(read_trajectory(tmp_path / "trajectory_kitti.txt").poses,
                               Tr @ poses @ geometry.inv(Tr), atol=1e-8)
    np.testing.assert_allclose(read_trajectory(tmp_path / "gt_kitti.txt").poses,
                               Tr @ gt.poses @ geometry.inv(Tr), atol=1e-8)
    np.testing.assert_allclose(read_trajectory(tmp_path / "gt_kitti_lidar.txt").poses, gt.poses, atol=1e-8)


@pytest.fixture(scope="module")
def kitti_run(kitti_extract, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    proc = flowslam("run", "--no-progress", "-f", "kiss-icp", "-b", "odometry", "-o", out, kitti_extract)
    assert proc.returncode == 0, proc.stderr
    return out / "latest"


def test_trajectory_kitti_is_in_camera0_like_the_official_poses(kitti_run, kitti_extract):
    Tr = KittiOdometry(kitti_extract).T_cam0_velo
    cam = read_trajectory(kitti_run / "trajectory_kitti.txt").poses
    lidar = read_trajectory(kitti_run / "trajectory_kitti_lidar.txt").poses
    tum = read_trajectory(kitti_run / "trajectory_tum.txt").poses
    assert len(cam) == len(lidar) == 16
    np.testing.assert_allclose(lidar, tum, atol=1e-8)  # the LiDAR-frame files agree
    np.testing.assert_allclose(cam[0], np.eye(4), atol=1e-12)  # KITTI: the first pose is the identity
    np.testing.assert_allclose(cam, Tr @ lidar @ np.linalg.inv(Tr), atol=1e-8)
    # camera 0 is z forward: the car drives ~12 m along z, not x as the LiDAR does
    assert cam[-1][2, 3] > 10 and abs(cam[-1][0, 3]) < 1.5
    assert lidar[-1][0, 3] > 10
    # the GT file of the run is exactly the official poses file
    official = read_trajectory(kitti_extract / "poses" / "00.txt").poses
    np.testing.assert_allclose(read_trajectory(kitti_run / "gt_kitti.txt").poses, official, rtol=0, atol=1e-9)


def test_eval_against_official_poses_gives_the_runs_metrics(kitti_run, kitti_extract, tmp_path):
    proc = flowslam("eval", kitti_run / "trajectory_kitti.txt", kitti_extract / "poses" / "00.txt",
                    "--json", tmp_path / "m.json")
    assert proc.returncode == 0, proc.stderr
    ours = json.loads((kitti_run / "metrics.json").read_text())
    theirs = json.loads((tmp_path / "m.json").read_text())
    assert theirs["n_poses_matched"] == ours["n_poses_matched"] == 16
    assert theirs["ape"]["alignment"] == ours["ape"]["alignment"]
    for part in ("trans_m", "rot_deg"):
        for stat in ("rmse", "mean", "max"):
            assert theirs["ape"][part][stat] == pytest.approx(ours["ape"][part][stat], rel=1e-7, abs=1e-12)
            assert theirs["rpe"][0][part][stat] == pytest.approx(ours["rpe"][0][part][stat], rel=1e-7, abs=1e-12)
    assert theirs["path_length_m"] == pytest.approx(ours["path_length_m"], rel=1e-9)


def test_run_json_states_every_files_frame_and_format(kitti_run):
    files = json.loads((kitti_run / "run.json").read_text())["files"]
    on_disk = {p.name for p in kitti_run.iterdir()}
    assert set(files) == on_disk
    assert all(entry["format"] for entry in files.values())
    assert "camera 0" in files["trajectory_kitti.txt"]["frame"] and "camera 0" in files["gt_kitti.txt"]["frame"]
    for name in ("trajectory_tum.txt", "trajectory_kitti_lidar.txt", "gt_kitti_lidar.txt", "static_map.ply"):
        assert "camera" not in files[name]["frame"], name
