"""Each preset's amount of motion, over a short sequence on the reference sensor
(HDL-64E, 64 x 2048): static 0, dh ~100 and dt ~4,000 dynamic points per frame,
rush-hour >= 20 % of the points dynamic, kitti00-path ~1,500."""

from __future__ import annotations

import numpy as np
import pytest

from flowslam.errors import InputError

FRAMES = 12


def _dynamic_counts(preset: str, seed: int = 0):
    from flowslam.simulation.ground_truth import make_frame
    from flowslam.simulation.presets import get_preset
    from flowslam.simulation.raycast import Raycaster
    from flowslam.simulation.sensors import get_sensor
    from flowslam.simulation.simulator import build_scene

    sensor = get_sensor("hdl64")
    _, ego, world, actors = build_scene(get_preset(preset), FRAMES, seed, sensor)
    caster = Raycaster(world, actors, sensor)
    dyn, share = [], []
    for k in range(FRAMES):
        t0, t1 = float(ego.frame_times[k]), float(ego.frame_times[k + 1])
        f = make_frame(caster.cast(t0, ego.sensor, False), caster, ego.sensor, t0, t1, False,
                       np.random.default_rng(k))
        dyn.append(int(f.dynamic.sum()))
        share.append(f.dynamic.mean())
    return np.array(dyn), float(np.mean(share)), actors


def test_static_has_no_motion():
    dyn, _, actors = _dynamic_counts("static")
    assert dyn.max() == 0 and len(actors.actors) == 0


def test_dh_about_100_dynamic_points_per_frame():
    dyn, _, actors = _dynamic_counts("dh")
    assert 50 <= dyn.mean() <= 200, dyn
    assert dyn.max() < 1000


def test_dt_about_4000_dynamic_points_per_frame():
    dyn, _, actors = _dynamic_counts("dt")
    assert 2500 <= dyn.mean() <= 6000, dyn
    assert actors.count_by("role").get("convoy") == 1


def test_rush_hour_at_least_a_fifth_dynamic():
    dyn, share, actors = _dynamic_counts("rush-hour")
    assert share >= 0.20, share
    roles = actors.count_by("role")
    assert roles["walker"] > 200 and roles["vehicle"] > 30 and roles.get("oncoming", 0) > 5


def test_kitti00_path(kitti00_full_gt):
    dyn, _, _ = _dynamic_counts("kitti00-path")
    assert 700 <= dyn.mean() <= 3000, dyn


def test_unknown_preset_is_bad_input(tmp_path):
    from flowslam.simulation import simulate

    with pytest.raises(InputError, match="unknown preset"):
        simulate(tmp_path / "x", preset="traffic-jam")
