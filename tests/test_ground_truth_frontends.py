"""Frontends ``gt`` and ``gt-flow``: real AV2 pair against its ego motion, synthetic
sequences (missing flow -> counted fallback), datasets without flow -> clear error."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config import load_config
from flowslam.datasets import open_dataset
from flowslam.frame import Frame
from flowslam.errors import InputError
from flowslam.config import FlowOdometryConfig
from flowslam.fallbacks import summarize_fallbacks
from flowslam.frontends.ground_truth import (
    EXACT_FLOOR_FACTOR,
    GroundTruthFlowFrontend,
    exact_flow_options,
    make_gt_flow_frontend,
    make_gt_frontend,
)
from flowslam.registry import make_frontend

from test_flow_odometry import street_scene

log = logging.getLogger(__name__)


def motion_error(T, T_ref) -> tuple[float, float]:
    """(translation mm, rotation deg) of ``inv(T_ref) @ T``."""
    E = geometry.inv(T_ref) @ T
    return float(np.linalg.norm(E[:3, 3]) * 1e3), float(np.rad2deg(geometry.rotation_angle(E)))


# -- real data ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def av2(av2_log: Path):
    ds = open_dataset(av2_log)
    return ds, ds[0], ds[1]


@pytest.mark.parametrize("name", ["gt", "gt-flow"])
def test_av2_ego_motion(av2, av2_log: Path, name: str):
    ds, f0, f1 = av2
    frontend = make_frontend(name, load_config())
    assert frontend.name == name
    first = frontend.process(f0)
    assert first.T_prev_curr is None and first.index == 0
    out = frontend.process(f1)
    assert out.index == 1 and not out.stats["fallback"]

    T_1_0 = np.load(av2_log / "ego_motion.npz")["ego_motion"][0].astype(np.float64)  # T_{1<-0}
    T_gt = geometry.relative(ds.gt_poses[0], ds.gt_poses[1])  # T_prev_curr from the ego poses
    t_npz, r_npz = motion_error(out.T_prev_curr, geometry.inv(T_1_0))
    t_gt, r_gt = motion_error(out.T_prev_curr, T_gt)
    log.info("%s on the AV2 pair: vs ego_motion.npz %.4f mm %.6f deg; vs ego poses %.4f mm %.6f deg",
             name, t_npz, r_npz, t_gt, r_gt)
    # the flow labels were made with ego_motion.npz (float16-rounded translation): near exact
    assert t_npz < 0.05 and r_npz < 1e-4
    # the ego poses differ from ego_motion.npz by that rounding (0.82 mm)
    assert t_gt < 1.0 and r_gt < 1e-4

    np.testing.assert_array_equal(out.points, f0.points)
    np.testing.assert_array_equal(out.flow, f0.gt_flow)
    static = ~f0.gt_dynamic
    if name == "gt":
        np.testing.assert_array_equal(out.static_mask, static)
        assert out.stats["n_static"] == static.sum()
    else:
        assert out.static_mask is None and out.stats["n_static"] == len(f0.points)
    # the 2037 moving points are never inliers, so at most the static ones are
    assert out.stats["inliers"] <= static.sum()
    # a realistic covariance: the floor for exact flow (0.5 mm, 0.001 deg; the labels' own
    # rounding is 0.82 mm), not micrometres, and well below the estimated flows' (5 mm, 0.01 deg)
    std = np.sqrt(np.diag(out.covariance))
    assert np.all(std[3:] >= 0.0005) and np.all(std[:3] >= np.deg2rad(0.001))
    assert np.all(std[3:] < 0.002) and np.all(std[:3] < np.deg2rad(0.005))


def test_dataset_without_flow_is_a_clear_error(kitti_extract: Path):
    ds = open_dataset(kitti_extract)
    for factory in (make_gt_frontend, make_gt_flow_frontend):
        frontend = factory(load_config())
        frontend.process(ds[0])
        with pytest.raises(InputError) as info:
            frontend.process(ds[1])
        msg = str(info.value)
        assert "000000.bin (frame 0): has no ground-truth flow; the gt/gt-flow frontends need a dataset " \
               "with flow labels (simulated sequences, Argoverse 2 with flow_labels)" in msg


# -- synthetic sequences -----------------------------------------------------------


def synthetic_sequence(n_frames: int = 6, missing_flow: tuple[int, ...] = (), seed: int = 0) -> tuple[list[Frame], np.ndarray]:
    """Frames of a static street plus one car (instance 7) driving 10 m/s, seen by a
    sensor driving 12 m/s with a slight turn; GT flow, dynamic labels and instances.
    Returns (frames, poses T_world_sensor)."""
    rng = np.random.default_rng(seed)
    world = street_scene(rng, 12000)
    lo, hi = np.array([3.5, -3.5, -1.6]), np.array([14.0, -0.5, 0.5])  # the car's path: no clutter
    world = world[~np.all((world > lo) & (world < hi), axis=1)]
    car0 = rng.uniform([4, -3, -1.5], [8.5, -1, 0], size=(800, 3))
    step = geometry.from_euler("z", 1.5, t=[1.2, 0.0, 0.0], degrees=True)  # T_prev_curr, 0.1 s
    poses = geometry.compose_relatives(np.repeat(step[None], n_frames - 1, axis=0))
    car_velocity = np.array([10.0, 0.5, 0.0])  # m/s, world
    frames = []
    for k in range(n_frames):
        T_s_w = geometry.inv(poses[k])
        car_k = car0 + car_velocity * 0.1 * k
        pts = np.vstack([geometry.transform_points(T_s_w, world), geometry.transform_points(T_s_w, car_k)])
        flow = None
        if k + 1 < n_frames and k not in missing_flow:
            T_next_w = geometry.inv(poses[k + 1])
            nxt = np.vstack([geometry.transform_points(T_next_w, world),
                             geometry.transform_points(T_next_w, car_k + car_velocity * 0.1)])
            flow = nxt - pts
        dyn = np.r_[np.zeros(len(world), bool), np.ones(len(car0), bool)]
        frames.append(Frame(
            index=k, timestamp=100.0 + 0.1 * k, points=pts, gt_pose=poses[k], gt_flow=flow,
            gt_dynamic=dyn, gt_instance=np.r_[np.full(len(world), -1), np.full(len(car0), 7)],
            source=f"sim/{k:06d}",
        ))
    return frames, poses


@pytest.mark.parametrize("use_labels", [True, False])
def test_synthetic_sequence_exact(use_labels: bool):
    frames, poses = synthetic_sequence()
    frontend = GroundTruthFlowFrontend(use_labels=use_labels)
    outs = [frontend.process(f) for f in frames]
    for k in range(1, len(frames)):
        t_mm, r_deg = motion_error(outs[k].T_prev_curr, geometry.relative(poses[k - 1], poses[k]))
        assert t_mm < 1e-3 and r_deg < 1e-6
        assert outs[k].points is frames[k - 1].points
    if use_labels:
        np.testing.assert_array_equal(outs[1].instance_ids, frames[0].gt_instance)
    else:
        assert outs[1].instance_ids is None
    assert frontend.odometry.fallback_count == 0


def test_missing_flow_mid_sequence_falls_back_and_is_counted():
    frames, poses = synthetic_sequence(missing_flow=(2,))
    frontend = make_gt_frontend(load_config())
    outs = [frontend.process(f) for f in frames]
    fb = outs[3]  # uses frame 2, which has no flow
    assert fb.stats["fallback"] and fb.stats["fallback_code"] == "no_flow"
    assert "frame 2 has no ground-truth flow" in fb.stats["reason"]
    assert fb.points is None and fb.flow is None
    np.testing.assert_allclose(fb.T_prev_curr, outs[2].T_prev_curr, atol=1e-12)  # constant velocity
    assert np.all(np.diag(fb.covariance) > np.diag(outs[2].covariance))
    t_mm, _ = motion_error(outs[4].T_prev_curr, geometry.relative(poses[3], poses[4]))
    assert t_mm < 1e-3 and not outs[4].stats["fallback"]
    assert summarize_fallbacks([o.stats for o in outs]) == {
        "frames": 6, "fallbacks": 1, "by_reason": {"no_flow": 1},
    }


def test_first_pair_without_flow_is_an_error_and_missing_labels_too():
    frames, _ = synthetic_sequence(missing_flow=(0,))
    frontend = GroundTruthFlowFrontend(use_labels=False)
    frontend.process(frames[0])
    with pytest.raises(InputError, match=r"sim/000000 \(frame 0\): has no ground-truth flow"):
        frontend.process(frames[1])

    frames, _ = synthetic_sequence()
    for f in frames:
        f.gt_dynamic = None
    gt = GroundTruthFlowFrontend(use_labels=True)
    gt.process(frames[0])
    with pytest.raises(InputError, match="no dynamic labels.*gt-flow"):
        gt.process(frames[1])
    flow_only = GroundTruthFlowFrontend(use_labels=False)  # gt-flow does not need them
    flow_only.process(frames[0])
    assert not flow_only.process(frames[1]).stats["fallback"]


def test_factories_take_the_flow_odometry_section():
    custom = FlowOdometryConfig(min_static_points=100000)
    frontend = make_gt_frontend(SimpleNamespace(flow_odometry=custom))
    # the section's options, with the covariance floor for exact flow
    assert frontend.odometry.config == exact_flow_options(custom)
    assert frontend.odometry.config.min_static_points == 100000
    assert frontend.odometry.config.min_translation_std_m == custom.min_translation_std_m * EXACT_FLOOR_FACTOR
    frames, _ = synthetic_sequence(n_frames=2)
    frontend.process(frames[0])
    assert frontend.process(frames[1]).stats["fallback_code"] == "few_points"
    assert make_gt_flow_frontend(object()).odometry.config == exact_flow_options(FlowOdometryConfig())
