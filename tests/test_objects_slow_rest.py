"""``rest_min_speed_mps``: dynamic points that no accepted object holds become static where
their group's own flow says they do not move (median departure from the ego landings at
most ``rest_min_speed_mps``) and no point of it is a geometric mover. Exact constructed
geometry; real SciPy KD-trees."""

import numpy as np

from flowslam import geometry
from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.objects import refine_objects

DT = 0.1
HEIGHT = 1.73  # sensor above the flat ground (m)
T_EGO = geometry.inv(geometry.from_euler("z", 0.05, t=[0.8, 0.1, 0.0]))  # T_{k,k-1}: 0.8 m forward, turning


def _group(x: float, y: float, n: int, rng) -> np.ndarray:
    """``n`` points of a small upright blob (fewer than ``min_points``: no object, no ICP)
    at (x, y), 0.6-1.6 m above the ground (clear of its surface)."""
    xy = np.array([x, y]) + (rng.random((n, 2)) - 0.5) * 0.4
    return np.column_stack([xy, -HEIGHT + 0.6 + rng.random(n)])


def test_a_flagged_group_whose_own_flow_does_not_move_becomes_static_and_a_moving_one_stays():
    """Scan k holds only the ground, so every flagged group's ego landings are off its
    surface (as where the static refinement's target drops the network's dynamic landings).
    Residual flows (m per 0.1 s): ``still`` 0.02 (0.2 m/s), ``walker`` 0.15 (1.5 m/s),
    ``mixed`` seven points at 0.1 and five at 0 (median 1 m/s: the group, not each point,
    decides), ``flagged`` 0.02 but one point a geometric mover (the geometry says it
    moved), ``body`` the ego vehicle's own returns within ``min_range_m`` (never
    relabelled). Without the option (0) all stay dynamic; at 0.5 m/s only ``still`` becomes
    static, with the ego motion's flow."""
    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-5, 40, 4000), rng.uniform(-8, 8, 4000), np.full(4000, -HEIGHT)])
    still, walker, mixed = _group(20.0, 3.0, 12, rng), _group(25.0, -4.0, 12, rng), _group(15.0, 6.0, 12, rng)
    flagged = _group(30.0, 0.0, 12, rng)
    body = np.column_stack([rng.uniform(-1.6, -1.4, 10), rng.uniform(-0.7, -0.5, 10), np.full(10, -0.6)])
    prev = np.concatenate([ground, still, walker, mixed, flagged, body])
    part = np.repeat(np.arange(6), [len(ground), len(still), len(walker), len(mixed), len(flagged), len(body)])
    curr = geometry.transform_points(T_EGO, ground)
    ego_flow = geometry.rigid_flow(T_EGO, prev)
    flow = ego_flow.copy()
    flow[part == 1] += [0.02, 0.0, 0.0]
    flow[part == 2] += [0.0, 0.15, 0.0]
    flow[np.flatnonzero(part == 3)[:7]] += [0.1, 0.0, 0.0]
    flow[part == 4] += [0.02, 0.0, 0.0]
    dynamic = part > 0
    movers = np.zeros(len(prev), dtype=bool)
    movers[np.flatnonzero(part == 4)[0]] = True

    configs = (ObjectRefinementConfig(rest_min_speed_mps=speed) for speed in (0.0, 0.5))
    without, with_ = (refine_objects(prev, flow, dynamic, curr, T_EGO, DT, c, movers=movers) for c in configs)

    assert without.dynamic[part > 0].all() and without.stats["rest_static_slow"] == 0
    assert not with_.dynamic[part == 1].any() and with_.stats["rest_static_slow"] == len(still)
    np.testing.assert_allclose(with_.flow[part == 1], ego_flow[part == 1], atol=1e-12)
    assert with_.dynamic[part >= 2].all()
    keep = part != 1
    assert np.array_equal(without.dynamic[keep], with_.dynamic[keep])
    np.testing.assert_array_equal(without.flow[keep], with_.flow[keep])
    # the slow group's points no longer make an unregistered instance
    assert (with_.instance[part == 1] == -1).all()
