"""The ego's route: block loops come back to places already seen; a given trajectory
(the real KITTI-00 path, camera-0 frame) is put on the ground plane correctly."""

from __future__ import annotations

import numpy as np
import pytest

from flowslam import geometry
from flowslam.errors import InputError


def test_loop_route_comes_back():
    from flowslam.simulation.ego_path import loop_route
    from flowslam.simulation.presets import get_preset
    from flowslam.simulation.roads import grid_network

    p = get_preset("dt")
    rng = np.random.default_rng(4)
    net = grid_network(rng, *p.grid, block=p.block)
    ego = loop_route(net, p.grid, rng, 300, 0.1, p.cruise, 0.3, 15.0)
    x, y, yaw = ego.sensor.at(ego.frame_times[:300])
    P = np.stack([x, y], 1)
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert steps.max() < 1.6  # <= 16 m/s
    far_apart = np.abs(np.arange(300)[:, None] - np.arange(300)[None]) > 100
    d = np.linalg.norm(P[:, None] - P[None], axis=2)
    assert (np.where(far_apart, d, np.inf) < 1.0).sum() > 20  # revisits (loop closure)
    # heading follows the direction of travel
    h = np.arctan2(np.diff(P[:, 1]), np.diff(P[:, 0]))
    assert np.abs(np.angle(np.exp(1j * (h - yaw[:-1])))).max() < np.deg2rad(8)


def test_kitti_camera_path_on_the_ground(kitti00_full_gt):
    from flowslam.simulation.ego_path import read_ground_path
    from flowslam.trajectory import read_trajectory

    times_file = kitti00_full_gt.with_name("kitti00_gt_times.txt")
    t, x, y, yaw = read_ground_path(kitti00_full_gt, times_file)
    cam = read_trajectory(kitti00_full_gt).poses
    assert len(t) == len(cam) == 4541 and t[0] == 0.0 and np.all(np.diff(t) > 0)
    # camera z forward -> x, camera x right -> -y
    assert np.allclose(x, cam[:, 2, 3]) and np.allclose(y, -cam[:, 0, 3])
    assert x[0] == pytest.approx(0.0, abs=1e-6) and yaw[0] == pytest.approx(0.0, abs=1e-6)
    # the car drives forward: heading along the displacement where it moves
    d = np.stack([np.diff(x), np.diff(y)], 1)
    moving = np.linalg.norm(d, axis=1) > 0.3
    h = np.arctan2(d[moving, 1], d[moving, 0])
    assert np.median(np.abs(np.angle(np.exp(1j * (h - yaw[:-1][moving]))))) < np.deg2rad(1.0)
    # ~3.7 km; the ground path is as long as the 3D one (nearly flat)
    length2d = np.linalg.norm(d, axis=1).sum()
    length3d = np.linalg.norm(np.diff(cam[:, :3, 3], axis=0), axis=1).sum()
    assert 3600 < length2d < 3800 and abs(length2d - length3d) / length3d < 0.005


def test_simulated_kitti_path_follows_the_file(kitti00_full_gt, tmp_path):
    from flowslam.datasets import open_dataset
    from flowslam.simulation import simulate
    from flowslam.simulation.ego_path import read_ground_path
    from flowslam.simulation.paths import planar_T

    simulate(tmp_path / "k", preset="kitti00-path", frames=5, sensor="vlp16", columns=90, workers=1)
    ds = open_dataset(tmp_path / "k")
    t, x, y, yaw = read_ground_path(kitti00_full_gt, kitti00_full_gt.with_name("kitti00_gt_times.txt"))
    T = planar_T(x[:5], y[:5], yaw[:5], 1.73)
    expected = geometry.inv(T[0])[None] @ T
    assert np.allclose(ds.gt_poses, expected, atol=1e-6)
    assert np.allclose(ds.timestamps, t[:5], atol=1e-6)


def test_too_many_frames_for_the_trajectory(tmp_path):
    from flowslam.simulation import simulate

    traj = tmp_path / "short.txt"
    lines = [f"1 0 0 {0.5 * k} 0 1 0 0 0 0 1 0" for k in range(10)]  # z-up: x forward
    traj.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="at most 9 frames"):
        simulate(tmp_path / "out", preset="static", frames=20, trajectory=traj, sensor="vlp16", columns=90)
    m = simulate(tmp_path / "ok", preset="static", frames=9, trajectory=traj, sensor="vlp16", columns=90, workers=1)
    assert m["frames"] == 9
