"""``flat_motion``: every point left dynamic keeps its ego landing's height (objects move on
the ground). Exact constructed geometry; real SciPy KD-trees."""

import numpy as np

from flowslam import geometry
from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.objects import _level, refine_objects

DT = 0.1
# T_{k,k-1}: 1 m forward, 2 degrees of yaw and 0.3 degrees of pitch (a crest): the ego
# landings themselves change height, and the level flow must follow them, not z = const
T_EGO = geometry.inv(geometry.from_euler("zy", [2.0, 0.3], degrees=True, t=[1.0, 0.0, 0.05]))


def test_level_keeps_the_ego_landing_height_and_the_horizontal_departure():
    rng = np.random.default_rng(11)
    source = rng.uniform(-20, 20, (50, 3))
    ego = geometry.rigid_flow(T_EGO, source)
    flow = ego + [0.3, -0.2, 0.07]  # a mover's flow that also climbs 7 cm
    idx = np.arange(0, 50, 2)
    levelled = flow.copy()

    _level(source, levelled, idx, T_EGO)

    assert np.allclose(levelled[idx, 2], ego[idx, 2]) and np.allclose(levelled[idx, :2], flow[idx, :2])
    rest = np.setdiff1d(np.arange(50), idx)
    assert np.array_equal(levelled[rest], flow[rest])


def test_a_flagged_mover_keeps_its_ego_landing_height_only_with_flat_motion():
    """A walker at 90 m (beyond ``max_range_m``: no ICP, it keeps the network's flow, which
    moves it 0.15 m along x and 4 cm up) on empty ground: it stays dynamic either way; with
    ``flat_motion`` its flow departs from the ego landing only horizontally."""
    rng = np.random.default_rng(12)
    ground = np.column_stack([rng.uniform(-5, 40, 3000), rng.uniform(-8, 8, 3000), np.full(3000, -1.73)])
    walker = np.column_stack([90.0 + rng.uniform(-0.2, 0.2, 60), rng.uniform(1.8, 2.2, 60), rng.uniform(-1.73, 0, 60)])
    prev = np.concatenate([ground, walker])
    curr = geometry.transform_points(T_EGO, ground)
    flagged = np.arange(len(prev)) >= len(ground)
    flow = geometry.rigid_flow(T_EGO, prev)
    flow[flagged] += [0.15, 0.0, 0.04]

    kept, level = (refine_objects(prev, flow, flagged, curr, T_EGO, DT, ObjectRefinementConfig(flat_motion=on))
                   for on in (False, True))

    assert kept.dynamic[flagged].all() and level.dynamic[flagged].all()
    ego = geometry.rigid_flow(T_EGO, prev[flagged])
    assert np.allclose(kept.flow[flagged] - ego, [0.15, 0.0, 0.04])
    assert np.allclose(level.flow[flagged] - ego, [0.15, 0.0, 0.0])
    assert np.array_equal(kept.flow[~flagged], level.flow[~flagged])  # static points: the ego motion's
