"""`flowslam run` end to end on the real KITTI extract, and `flowslam eval` / `config` / `plugins`."""

import json

import numpy as np
import pytest

from flowslam.evaluation import evaluate
from flowslam.trajectory import read_trajectory

from cli_helpers import flowslam


@pytest.fixture(scope="module")
def kitti_run(kitti_extract, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    proc = flowslam("run", "--frontend", "kiss-icp", "--backend", "odometry", "-o", out, kitti_extract)
    assert proc.returncode == 0, proc.stderr
    return out, proc


def test_run_writes_every_output(kitti_run):
    out, proc = kitti_run
    latest = out / "latest"
    assert latest.is_symlink() and latest.resolve().parent == out.resolve()
    for name in ["trajectory_tum.txt", "trajectory_kitti.txt", "trajectory_kitti_lidar.txt", "odometry_tum.txt",
                 "gt_tum.txt", "gt_kitti.txt", "gt_kitti_lidar.txt", "config.yaml", "metrics.json", "run.json", "trajectory_topview.png",
                 "static_map.ply", "static_map.pcd"]:
        assert (latest / name).is_file(), name
    assert (latest / "trajectory_topview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    run = json.loads((latest / "run.json").read_text())
    assert run["frames_processed"] == 16 and run["error"] is None
    tum = read_trajectory(latest / "trajectory_tum.txt")
    assert len(tum) == 16
    np.testing.assert_allclose(tum.timestamps[:3], [0.0, 0.1037359, 0.2073381], atol=1e-6)
    np.testing.assert_allclose(tum.poses[0], np.eye(4), atol=1e-9)
    assert "results in" in proc.stdout


def test_kiss_icp_accuracy_on_real_kitti(kitti_run, kitti_extract):
    """KISS-ICP vs the ICP reference (the official GT of these frames is a constant-velocity fill)."""
    latest = kitti_run[0] / "latest"
    est = read_trajectory(latest / "trajectory_kitti_lidar.txt")  # the reference is in the LiDAR frame
    ref = read_trajectory(kitti_extract / "reference_icp_lidar.txt")
    m_ref = evaluate(est, ref)
    assert m_ref["rpe"][0]["trans_m"]["rmse"] < 0.025  # 1.96 cm measured (2.26 cm without the KITTI correction)
    assert m_ref["end_point_error"]["trans_m"] < 0.3
    # against the official GT: ~10 cm per step, as the data README predicts for any correct method
    m_gt = json.loads((latest / "metrics.json").read_text())
    assert 0.05 < m_gt["rpe"][0]["trans_m"]["rmse"] < 0.15
    assert m_gt["n_poses_matched"] == 16


def test_eval_command_matches_library(kitti_run, kitti_extract, tmp_path):
    latest = kitti_run[0] / "latest"
    ref = kitti_extract / "reference_icp_lidar.txt"
    proc = flowslam("eval", latest / "trajectory_kitti_lidar.txt", ref, "--delta", "1", "--delta", "5m",
                    "--json", tmp_path / "m.json")
    assert proc.returncode == 0, proc.stderr
    saved = json.loads((tmp_path / "m.json").read_text())
    lib = evaluate(read_trajectory(latest / "trajectory_kitti_lidar.txt"), read_trajectory(ref))
    assert saved["rpe"][0]["trans_m"]["rmse"] == pytest.approx(lib["rpe"][0]["trans_m"]["rmse"], abs=1e-12)
    assert saved["rpe"][1]["delta_unit"] == "m" and saved["rpe"][1]["n_pairs"] > 0
    assert "RPE" in proc.stdout


def test_config_dump_is_reusable(tmp_path):
    proc = flowslam("config")
    assert proc.returncode == 0 and "kiss_icp:" in proc.stdout
    (tmp_path / "c.yaml").write_text(proc.stdout.replace("max_points_per_voxel: 20", "max_points_per_voxel: 7"))
    again = flowslam("config", "-c", tmp_path / "c.yaml")
    assert "max_points_per_voxel: 7" in again.stdout


def test_plugins_lists_builtins():
    proc = flowslam("plugins")
    assert proc.returncode == 0
    assert "kiss-icp" in proc.stdout and "odometry" in proc.stdout and "rosbag" in proc.stdout


def test_isam2_a_loam_equals_odometry_backend(kitti_run, kitti_extract, tmp_path):
    """Same kiss-icp measurements, no loops, no mapping stage: the iSAM2 optimum is the
    composed chain."""
    proc = flowslam("run", "--no-progress", "-f", "kiss-icp", "-b", "isam2", "--variant", "a-loam",
                    "--no-mapping", "-o", tmp_path, kitti_extract)
    assert proc.returncode == 0, proc.stderr
    isam = read_trajectory(tmp_path / "latest" / "trajectory_kitti.txt")
    odo = read_trajectory(kitti_run[0] / "latest" / "trajectory_kitti.txt")
    np.testing.assert_allclose(isam.poses, odo.poses, atol=1e-6)
    run = json.loads((tmp_path / "latest" / "run.json").read_text())
    assert run["backend_stats"]["scans"] == 16 and run["loop_closures"] == 0
    assert run["loop_closure"] is False  # a-loam: no loop closer was built
    assert run["mapping"] is None


def test_output_plot_off_writes_no_top_view(kitti_extract, tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text("output: {plot: false, static_map: false}\n")
    proc = flowslam("run", "--no-progress", "-n", "3", "-c", config, "-o", tmp_path / "r", kitti_extract)
    assert proc.returncode == 0, proc.stderr
    latest = tmp_path / "r" / "latest"
    assert (latest / "trajectory_kitti.txt").is_file()
    assert not (latest / "trajectory_topview.png").exists() and not (latest / "static_map.ply").exists()
