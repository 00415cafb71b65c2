"""Moving objects: ego-compensated velocity of a 10 m/s object, world frame, CSV."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from flowslam import geometry
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput
from flowslam.moving_objects import CSV_HEADER, MovingObjectsLog, ego_compensated_flow, moving_objects

from test_ground_truth_frontends import synthetic_sequence

DT = 0.1002  # s, like the AV2 pair


def scene_pair(seed: int = 0):
    """Scan k-1 with static points and an object driving 10 m/s in the world (heading
    30 deg), seen from a sensor driving 15 m/s while turning. Returns what a frontend
    reports plus the world truth."""
    rng = np.random.default_rng(seed)
    T_world_prev = geometry.from_euler("zyx", [40.0, 1.0, -0.5], t=[100.0, -50.0, 2.0], degrees=True)
    T_prev_curr = geometry.from_euler("z", 2.0, t=[15.0 * DT, 0.1, 0.0], degrees=True)
    T_world_curr = T_world_prev @ T_prev_curr
    v_world = 10.0 * np.array([np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30)), 0.0])

    static_w = geometry.transform_points(T_world_prev, rng.uniform(-30, 30, (3000, 3)))
    obj_w = geometry.transform_points(T_world_prev, rng.uniform([5, 2, -1], [9, 4, 0.5], (400, 3)))
    pts_w = np.vstack([static_w, obj_w])
    next_w = np.vstack([static_w, obj_w + v_world * DT])
    points = geometry.transform_points(geometry.inv(T_world_prev), pts_w)
    flow = geometry.transform_points(geometry.inv(T_world_curr), next_w) - points  # AV2 convention
    dynamic = np.r_[np.zeros(3000, bool), np.ones(400, bool)]
    ids = np.r_[np.full(3000, -1), np.full(400, 42)]
    return points, flow, ids, dynamic, T_prev_curr, T_world_prev, v_world, obj_w.mean(axis=0)


def test_ego_compensated_flow_is_zero_for_static_points():
    points, flow, ids, dynamic, T_prev_curr, *_ = scene_pair()
    d = ego_compensated_flow(points, flow, T_prev_curr)
    assert np.abs(d[~dynamic]).max() < 1e-9
    assert np.linalg.norm(d[dynamic], axis=1) == pytest.approx(10.0 * DT, rel=1e-9)


def test_object_velocity_10_mps_in_world():
    points, flow, ids, dynamic, T_prev_curr, T_world_prev, v_world, c_world = scene_pair()
    objs = moving_objects(points, flow, ids, T_prev_curr, DT, ~dynamic, frame=5, timestamp=12.5)
    assert len(objs) == 1
    ob = objs[0]
    assert (ob.frame, ob.timestamp, ob.instance_id, ob.n_points) == (5, 12.5, 42, 400)
    c, v = ob.in_world(T_world_prev)
    assert np.linalg.norm(v - v_world) < 0.01 * 10.0  # within 1% (exact here)
    np.testing.assert_allclose(v, v_world, atol=1e-9)
    np.testing.assert_allclose(c, c_world, atol=1e-9)
    np.testing.assert_allclose(ob.centroid, points[dynamic].mean(axis=0), atol=1e-12)


def test_noisy_flow_within_one_percent():
    points, flow, ids, dynamic, T_prev_curr, T_world_prev, v_world, _ = scene_pair(1)
    flow = flow + np.random.default_rng(1).normal(0, 0.05, flow.shape)  # 5 cm flow noise
    (ob,) = moving_objects(points, flow, ids, T_prev_curr, DT, ~dynamic)
    _, v = ob.in_world(T_world_prev)
    assert abs(np.linalg.norm(v) - 10.0) < 0.1 and np.linalg.norm(v - v_world) < 0.1


def test_static_instances_and_filters():
    points, flow, ids, dynamic, T_prev_curr, *_ = scene_pair()
    ids = ids.copy()
    ids[:100] = 3  # a parked car: static points with an instance id
    assert [o.instance_id for o in moving_objects(points, flow, ids, T_prev_curr, DT, ~dynamic)] == [42]
    both = moving_objects(points, flow, ids, T_prev_curr, DT, None)  # no mask: every instance
    assert [o.instance_id for o in both] == [3, 42] and np.linalg.norm(both[0].velocity) < 1e-9
    assert [o.instance_id for o in moving_objects(points, flow, ids, T_prev_curr, DT, None, min_speed=0.5)] == [42]
    assert moving_objects(points, flow, ids, T_prev_curr, DT, ~dynamic, min_points=401) == []
    with pytest.raises(ValueError, match="dt"):
        moving_objects(points, flow, ids, T_prev_curr, 0.0)


def test_log_on_output_and_csv(tmp_path: Path):
    points, flow, ids, dynamic, T_prev_curr, T_world_prev, v_world, c_world = scene_pair()
    log = MovingObjectsLog()
    f_prev = Frame(index=7, timestamp=1000.0, points=points)
    f_curr = Frame(index=8, timestamp=1000.0 + DT, points=points)
    log.on_output(f_prev, FrontendOutput(index=7, T_prev_curr=None))
    log.on_output(f_curr, FrontendOutput(index=8, T_prev_curr=T_prev_curr, points=points, flow=flow,
                                         static_mask=~dynamic, instance_ids=ids))
    path = log.write_csv(tmp_path / "out" / "moving_objects.csv", {7: T_world_prev, 8: np.eye(4)})
    with open(path) as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == CSV_HEADER == (
        "frame", "timestamp", "instance_id", "n_points", "cx", "cy", "cz", "vx", "vy", "vz", "speed",
        "track_id", "track_age", "sx", "sy", "sz")
    assert len(rows) == 2
    r = rows[1]
    assert (int(r[0]), float(r[1]), int(r[2]), int(r[3])) == (7, 1000.0, 42, 400)
    np.testing.assert_allclose([float(x) for x in r[4:7]], c_world, atol=1e-4)
    np.testing.assert_allclose([float(x) for x in r[7:10]], v_world, atol=1e-4)
    assert float(r[10]) == pytest.approx(10.0, abs=1e-4)
    assert (int(r[11]), int(r[12])) == (0, 0)  # the first track, first seen here
    own = points[(ids == 42) & dynamic]
    np.testing.assert_allclose([float(x) for x in r[13:16]], np.ptp(own, axis=0), atol=1e-3)  # sensor axes
    assert log.rows(poses=None)[0][4:7] == tuple(log.objects[0].centroid)  # sensor frame without poses
    assert log.rows({8: np.eye(4)}) == []  # no pose for scan 7: left out


def test_log_with_gt_frontend_on_a_sequence(tmp_path: Path):
    from flowslam.frontends.ground_truth import GroundTruthFlowFrontend

    frames, poses = synthetic_sequence(n_frames=4)
    frontend = GroundTruthFlowFrontend(use_labels=True)
    log = MovingObjectsLog()
    for f in frames:
        log.on_output(f, frontend.process(f))
    rows = log.rows(poses)
    assert [r[0] for r in rows] == [0, 1, 2] and {r[2] for r in rows} == {7}
    for r in rows:  # the car drives [10, 0.5, 0] m/s in the world
        np.testing.assert_allclose(r[7:10], [10.0, 0.5, 0.0], atol=1e-6)
    # one object, one track across the scans; its world centroids drawn on the top view
    assert [r[11] for r in rows] == [0, 0, 0] and [r[12] for r in rows] == [0, 1, 2]
    tracks = log.tracks(poses)
    assert list(tracks) == [0]
    np.testing.assert_allclose(tracks[0], [r[4:7] for r in rows])
    steps = np.diff(tracks[0], axis=0)  # 10.5 m/s x 0.1 s apart in the world
    np.testing.assert_allclose(steps, np.tile([1.0, 0.05, 0.0], (2, 1)), atol=1e-6)

    from flowslam.plotting import plot_top_view

    png = plot_top_view(tmp_path / "top.png", np.asarray(poses), tracks=tracks)
    assert png.stat().st_size > 10_000
