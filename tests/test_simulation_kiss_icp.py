"""KISS-ICP on a simulated ``static`` sequence registers it with a sane error: the town
has enough structure, and the poses, scans and timestamps agree."""

from __future__ import annotations

import numpy as np

from flowslam import geometry


def test_kiss_icp_on_static_sequence(tmp_path):
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend
    from flowslam.simulation import simulate

    simulate(tmp_path / "static", preset="static", frames=60, seed=1, sensor="hdl64", columns=1024)
    ds = open_dataset(tmp_path / "static")
    cfg = load_config()
    result = run_pipeline(ds, make_frontend("kiss-icp", cfg), make_backend("odometry", cfg))
    assert result.error is None
    est, gt = result.poses, ds.gt_poses[: len(result.poses)]
    assert len(est) == 60
    d = geometry.inv(geometry.relative(gt[:-1], gt[1:])) @ geometry.relative(est[:-1], est[1:])
    trans = geometry.translation_norm(d)
    rot = np.degrees(geometry.rotation_angle(d))
    assert np.median(trans) < 0.03, trans  # metres per frame (~0.9 m steps)
    assert np.sqrt(np.mean(trans**2)) < 0.1
    assert np.sqrt(np.mean(rot**2)) < 0.3
    length = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    end_error = np.linalg.norm(est[-1][:3, 3] - gt[-1][:3, 3])
    assert length > 25 and end_error / length < 0.02, (length, end_error)
