"""Dynamic points that no accepted object holds (``unregistered_instances``): they get
instances of their own, split as registered movers are, without changing flow or labels.
Exact constructed geometry; real SciPy KD-trees."""

import numpy as np

from flowslam import geometry
from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.objects import _number_unregistered, refine_objects

DT = 0.1
HEIGHT = 1.73  # sensor above the flat ground (m)
T_EGO = geometry.inv(geometry.from_euler("z", 0.0, t=[0.8, 0.0, 0.0]))  # T_{k,k-1}: 0.8 m forward


def _column(x: float, y: float, n: int, rng, width: float = 0.4, height: float = 1.7) -> np.ndarray:
    """``n`` points of an upright column (a walker) ``width`` wide standing at (x, y) on the ground."""
    xy = np.array([x, y]) + (rng.random((n, 2)) - 0.5) * width
    return np.column_stack([xy, -HEIGHT + rng.random(n) * height])


def test_dynamic_points_outside_accepted_objects_become_instances_split_like_registered_ones():
    """Object 0 is accepted (its points keep id 0). Object 1 was registered but not
    accepted: its two walkers 2 m apart become two instances; its static point keeps id 1.
    Loose dynamic points outside every object: a 40-point walker becomes an instance, a
    5-point fragment (under ``min_points``) stays without one. Speeds are the median
    departure from the ego landings over the interval (m/s)."""
    rng = np.random.default_rng(3)
    accepted = _column(10.0, 0.0, 30, rng)
    walker_a, walker_b = _column(15.0, 3.0, 30, rng), _column(15.0, 5.0, 25, rng)
    still = _column(15.0, 7.0, 1, rng)
    loose, fragment = _column(30.0, -4.0, 40, rng), _column(50.0, 10.0, 5, rng)
    source = np.concatenate([accepted, walker_a, walker_b, still, loose, fragment])
    n = [len(accepted), len(walker_a), len(walker_b), len(still), len(loose), len(fragment)]
    part = np.repeat(np.arange(6), n)
    instance = np.select([part == 0, part <= 3], [0, 1], -1).astype(np.int64)
    dynamic = part != 3
    flow = geometry.rigid_flow(T_EGO, source)
    flow[part == 1] += [0.1, 0.0, 0.0]  # 1 m/s
    flow[part == 2] += [0.0, 0.15, 0.0]  # 1.5 m/s
    flow[part == 4] += [0.2, 0.0, 0.0]  # 2 m/s
    objects = [{"points": 30, "accepted": True, "speed_mps": 1.0}, {"points": 56, "accepted": False}]
    c = ObjectRefinementConfig()

    added = _number_unregistered(source, flow.copy(), dynamic, instance, objects, T_EGO, DT, None, c)

    assert added == 3 and len(objects) == 5
    assert (instance[part == 0] == 0).all() and instance[part == 3][0] == 1
    ids = [np.unique(instance[part == k]) for k in (1, 2, 4)]
    assert all(len(i) == 1 and i[0] >= 2 for i in ids) and len({int(i[0]) for i in ids}) == 3
    assert (instance[part == 5] == -1).all()
    for k, speed in zip((1, 2, 4), (1.0, 1.5, 2.0)):
        entry = objects[int(instance[part == k][0])]
        assert entry["unregistered"] and not entry["accepted"] and entry["points"] == n[k]
        assert abs(entry["speed_mps"] - speed) < 1e-9


def test_a_flagged_mover_beyond_the_objects_range_gets_an_instance_with_the_option():
    """The network flags a walker at 90 m (beyond ``max_range_m``, 80 m here: no ICP) and returns of
    the ego vehicle's own body at 1.6 m (within ``min_range_m``). Both stay dynamic (nothing
    of scan k lies at their ego landings), with the same flow and labels either way; with
    ``unregistered_instances`` the walker is an instance, the ego body never is."""
    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-5, 40, 4000), rng.uniform(-8, 8, 4000), np.full(4000, -HEIGHT)])
    walker = _column(90.0, 2.0, 60, rng)
    body = np.column_stack([rng.uniform(-1.6, -1.4, 20), rng.uniform(-0.7, -0.5, 20), np.full(20, -0.6)])
    prev = np.concatenate([ground, walker, body])
    curr = geometry.transform_points(T_EGO, ground)
    is_walker = np.arange(len(prev)) >= len(ground)
    is_body = np.arange(len(prev)) >= len(ground) + len(walker)
    is_walker &= ~is_body
    flow = geometry.rigid_flow(T_EGO, prev)
    flow[is_walker] += [0.15, 0.0, 0.0]

    configs = [ObjectRefinementConfig(unregistered_instances=on, max_range_m=80.0) for on in (False, True)]
    results = [refine_objects(prev, flow, is_walker | is_body, curr, T_EGO, DT, c) for c in configs]

    without, with_ = results
    assert np.array_equal(without.dynamic, with_.dynamic) and np.allclose(without.flow, with_.flow)
    assert with_.dynamic[is_walker].all() and with_.dynamic[is_body].all()
    assert (without.instance[is_walker | is_body] == -1).all()
    assert without.stats["unregistered_instances"] == 0 and with_.stats["unregistered_instances"] == 1
    (walker_id,) = np.unique(with_.instance[is_walker])
    assert walker_id >= 0 and with_.objects[walker_id]["unregistered"]
    assert abs(with_.objects[walker_id]["speed_mps"] - 1.5) < 1e-9
    assert (with_.instance[is_body] == -1).all()
