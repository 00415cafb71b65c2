"""The streaming API (``flowslam.Slam``): scans fed one at a time give exactly what
``flowslam run`` gives on the same sequence, and the steps carry the per-scan outputs."""

import json

import numpy as np
import pytest

import flowslam
from flowslam.config import load_config
from flowslam.datasets import open_dataset
from flowslam.errors import InputError
from flowslam.run import run_sequence
from flowslam.trajectory import read_trajectory


@pytest.mark.parametrize("frontend, backend", [("kiss-icp", "isam2"), ("ssf", "odometry")])
def test_stream_equals_run(kitti_extract, tmp_path, frontend, backend):
    n = 16 if frontend == "kiss-icp" else 6
    cfg = load_config(frontend=frontend, backend=backend, output_dir=str(tmp_path / "r"),
                      **{"dataset.max_frames": n, "output.plot": False})
    outcome = run_sequence(kitti_extract, cfg)
    outcome.raise_for_error()

    slam = flowslam.Slam(cfg)
    dataset = open_dataset(kitti_extract, cfg.dataset)
    steps = [slam.register_frame(f.points, f.timestamp, point_times=f.point_times, intensity=f.intensity)
             for f in (dataset[i] for i in range(n))]
    stream = slam.trajectory()
    assert len(stream) == n and [s.index for s in steps] == list(range(n))
    # Equal to round-off: kiss-icp's multi-threaded (TBB) sums are not bit-identical from
    # one run to the next, not even between two `flowslam run`s.
    np.testing.assert_allclose(stream.poses, outcome.result.poses, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(stream.timestamps, outcome.result.timestamps)
    assert steps[0].T_prev_curr is None and steps[-1].covariance.shape == (6, 6)
    np.testing.assert_array_equal(steps[-1].T_world_sensor, slam.backend.latest_pose())
    if frontend == "ssf":  # per-point outputs refer to the previous scan
        assert steps[-1].points.shape == steps[-1].flow.shape and steps[-1].static_mask.dtype == bool

    written = slam.save(tmp_path / "mine")
    assert written[-1].name == "run.json"
    saved = read_trajectory(tmp_path / "mine" / "trajectory_tum.txt")
    np.testing.assert_allclose(saved.positions, read_trajectory(outcome.run_dir / "trajectory_tum.txt").positions,
                               rtol=0, atol=1e-8)
    info = json.loads((tmp_path / "mine" / "run.json").read_text())
    assert info["frames_processed"] == n and info["complete"] is True
    assert (tmp_path / "mine" / "static_map.ply").is_file()


def test_register_frame_refuses_bad_scans_and_keeps_its_state(kitti_extract):
    slam = flowslam.Slam(load_config())
    frame = open_dataset(kitti_extract)[0]
    slam.register_frame(frame.points, 1.0)
    with pytest.raises(InputError, match="not after the last scan"):
        slam.register_frame(frame.points, 1.0)
    with pytest.raises(InputError, match="valid points"):
        slam.register_frame(np.full((500, 3), np.nan), 1.1)
    step = slam.register_frame(frame.points, 1.1)
    assert step.index == 1 and len(slam.trajectory()) == 2
    np.testing.assert_allclose(step.T_prev_curr, np.eye(4), atol=0.02)  # the same scan again
