"""`flowslam simulate` and `flowslam demo` through the real CLI (small settings for speed)."""

import json

import numpy as np

from flowslam.datasets import open_dataset

from cli_helpers import assert_one_line_error, flowslam


def test_simulate_writes_a_readable_sequence_with_preview(tmp_path):
    out = tmp_path / "sim"
    proc = flowslam("simulate", "--preset", "dh", "--frames", "4", "--seed", "7", "--sensor", "vlp16",
                    "--preview", "--no-progress", out)
    assert proc.returncode == 0, proc.stderr
    assert "4 frames of vlp16 (dh, seed 7)" in proc.stdout
    assert (out / "preview.png").read_bytes()[:4] == b"\x89PNG"
    ds = open_dataset(out)
    assert len(ds) == 4 and ds[0].gt_flow is not None and ds.gt_poses is not None
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["seed"] == 7 and manifest["preset"] == "dh"


def test_simulate_bad_preset_is_one_line(tmp_path):
    assert_one_line_error(flowslam("simulate", "--preset", "nope", "--no-progress", tmp_path / "x"), "nope")


def test_demo_runs_each_backend_on_the_same_measurements(tmp_path):
    proc = flowslam("demo", "-f", "gt", "--cache-dir", tmp_path / "cache", "-o", tmp_path / "out", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert "gt" in proc.stdout and "isam2" in proc.stdout and "odometry" in proc.stdout
    demo_dir = (tmp_path / "out" / "latest").resolve()
    runs = sorted(p for p in demo_dir.iterdir() if p.is_dir() and not p.is_symlink())
    assert [r.name.split("_", 2)[2] for r in runs] == ["gt_odometry", "gt_isam2"]
    for run in runs:
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["rpe"][0]["trans_m"]["rmse"] < 0.01  # exact GT flow: mm-level odometry
        assert (run / "trajectory_topview.png").is_file()
    # the isam2 run found the demo route's loop, and the replayed odometry is the recorded one
    info = json.loads((runs[1] / "run.json").read_text())
    assert info["loop_closures"] >= 1
    odo = [np.loadtxt(r / "odometry_tum.txt") for r in runs]
    np.testing.assert_allclose(odo[0][:, 1:], odo[1][:, 1:], atol=1e-9)
