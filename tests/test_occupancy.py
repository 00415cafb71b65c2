"""A moving instance wider than a person that older scans saw in place becomes static
(``objects.occupied_release_share``); a car that was elsewhere, a walker in place and an
instance too slow to have left its place are not released. Real scan surfaces (cube index),
no network. Frames: world = sensor frame k-1; each older scan in its own sensor frame, the
sensor 1 m further back per scan along x; metres, seconds."""

import numpy as np
import pytest

from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import ScanSurface
from flowslam.sceneflow.refinement.objects import ObjectRefinement
from flowslam.sceneflow.refinement.occupancy import OlderSurface, occupied_share, release_occupied

DT = 0.1
SPACING = 0.05


def _translation(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _car(x0: float, y0: float = 10.0, length: float = 4.0, step: float = SPACING) -> np.ndarray:
    """The side a car 4 m long shows the sensor: a vertical face from x0 along x at y0, 0.3-1.5 m
    above the ground (z -1.5..-0.3 in the sensor frame, ground at -1.8)."""
    x, z = np.meshgrid(np.arange(x0, x0 + length, step), np.arange(-1.5, -0.3, step))
    return np.stack([x.ravel(), np.full(x.size, y0), z.ravel()], axis=1)


def _olders(world_scans: list[np.ndarray], first_back: int = 4) -> list[OlderSurface]:
    """Older scans ``first_back``, ``first_back`` + 1, ... before scan k-1, given in the world
    frame; the sensor stood ``back`` metres behind scan k-1's position along x."""
    olders = []
    for i, world in enumerate(world_scans):
        back = first_back + i
        T_old_prev = _translation(float(back))  # the world point x is at x + back in that scan's frame
        olders.append(OlderSurface(ScanSurface(world + [back, 0.0, 0.0]), T_old_prev, back))
    return olders


def _result(source: np.ndarray, moving: np.ndarray, flow: np.ndarray) -> ObjectRefinement:
    """One accepted moving instance (id 0) holding the ``moving`` points with ``flow``."""
    dynamic = np.asarray(moving, bool).copy()
    instance = np.where(dynamic, 0, -1)
    full_flow = np.where(dynamic[:, None], flow, 0.0)
    return ObjectRefinement(full_flow, dynamic, instance, [{"accepted": True, "speed_mps": 5.0}])


def _release(source, result, olders, **options) -> int:
    c = ObjectRefinementConfig(occupied_release_share=0.8, **options)
    return release_occupied(source, result, None, np.eye(4), DT, olders, c)


def test_occupied_share_counts_points_near_any_older_scan():
    points = np.array([[0.0, 10.0, -1.0], [1.0, 10.0, -1.0], [2.0, 10.0, -1.0], [3.0, 10.0, -1.0]])
    # one older scan saw the first point 0.1 m off and the third 0.5 m off, another the second 0.15 m off;
    # the fourth is 1.1 m from them all
    olders = _olders([np.array([[0.0, 10.1, -1.0], [2.0, 10.5, -1.0]]), np.array([[1.0, 9.85, -1.0]])])
    assert occupied_share(points, olders, 0.2) == pytest.approx(0.5)
    assert occupied_share(points, olders, 0.6) == pytest.approx(0.75)
    assert occupied_share(points, olders, 1.2) == pytest.approx(1.0)
    assert occupied_share(points, olders, 0.05) == pytest.approx(0.0)


def test_a_parked_car_the_older_scans_saw_in_place_is_released():
    car = _car(0.0)
    source = np.concatenate([car, _car(-10.0, y0=-8.0)])  # a second, unrelated body
    is_car = np.arange(len(source)) < len(car)
    # its ICP slid it 0.5 m along x (5 m/s); the older scans saw it where it stands, sparsely (0.2 m rings)
    result = _result(source, is_car, [0.5, 0.0, 0.0])
    olders = _olders([_car(0.0, step=0.2), _car(0.05, step=0.2)])
    released = _release(source, result, olders)
    assert released == is_car.sum()
    assert not result.dynamic.any() and np.all(result.instance == -1)
    assert np.allclose(result.flow, 0.0)  # the ego-rigid flow of a sensor standing still
    assert result.objects[0]["released"] and not result.objects[0]["accepted"]
    assert result.objects[0]["occupied_share"] == pytest.approx(1.0)
    assert result.objects[0]["moved_share"] < 0.6  # 2-2.5 m back it would have stood on its own rear half only


def test_a_car_the_older_scans_saw_elsewhere_keeps_moving():
    car = _car(0.0)
    result = _result(car, np.ones(len(car), bool), [0.5, 0.0, 0.0])
    # 0.4-0.5 s back it was 2.0-2.5 m further back along x: its rear 2 m overlap, the front half does not
    olders = _olders([_car(-2.0, step=0.2), _car(-2.5, step=0.2)])
    assert _release(car, result, olders) == 0
    assert result.dynamic.all() and np.all(result.instance == 0)
    assert np.allclose(result.flow, [0.5, 0.0, 0.0])


def test_a_bus_driving_along_its_own_side_keeps_moving():
    bus = _car(0.0, length=12.0)
    result = _result(bus, np.ones(len(bus), bool), [0.5, 0.0, 0.0])
    # 4 and 5 scans back it stood 2.0 and 2.5 m further back: its old side covers 10 of its 12 m now ...
    olders = _olders([_car(-2.0, length=12.0, step=0.2), _car(-2.5, length=12.0, step=0.2)])
    assert occupied_share(bus, olders, 0.2) >= 0.8
    # ... and all of it moved back by its motion, so the older scans do not prefer its standing still
    assert occupied_share(bus, olders, 0.2, step=np.array([0.5, 0.0, 0.0])) > 0.99
    assert _release(bus, result, olders) == 0
    assert result.dynamic.all()


def test_walkers_and_slow_instances_are_not_asked():
    walker = _car(0.0, length=0.5)  # 0.5 m wide: a person
    result = _result(walker, np.ones(len(walker), bool), [0.1, 0.0, 0.0])
    assert _release(walker, result, _olders([_car(0.0, length=0.5, step=0.2)])) == 0
    assert result.dynamic.all()
    car = _car(0.0)
    # 0.5 m/s for 0.4 s: 0.2 m, less than release_min_shift_m (0.4): it may not have left its place yet
    slow = _result(car, np.ones(len(car), bool), [0.05, 0.0, 0.0])
    assert _release(car, slow, _olders([_car(0.0, step=0.2)])) == 0
    assert slow.dynamic.all()
    # nor can the older scan tell it from a body standing still: 0.2 m back is within the radius too
    assert _release(car, slow, _olders([_car(0.0, step=0.2)]), release_min_shift_m=0.1) == 0
    assert _release(car, slow, _olders([_car(0.0, step=0.2)]), release_min_shift_m=0.1,
                    occupied_motion_margin=0.0) == len(car)


def test_off_or_without_older_scans_nothing_is_released():
    car = _car(0.0)
    result = _result(car, np.ones(len(car), bool), [0.5, 0.0, 0.0])
    olders = _olders([_car(0.0, step=0.2)])
    c = ObjectRefinementConfig(occupied_release_share=0.0)  # off
    assert release_occupied(car, result, None, np.eye(4), DT, olders, c) == 0
    assert _release(car, result, []) == 0
    assert result.dynamic.all()


def test_the_objects_stage_asks_the_surfaces_it_kept_placed_with_its_own_poses():
    """``ObjectsStage`` keeps each scan k's surface with its measured pose and asks those of the
    scans ``occupied_from_scans`` to ``occupied_to_scans`` before scan k-1: the ego drives 1 m
    per scan past a parked car that each pair's objects call moving; from the pair whose scan
    k-1 has a kept scan 4 back, the car is released, and at most the scans needed are kept."""
    from flowslam.config import SsfConfig
    from flowslam.frame import Frame
    from frontends.ssf_stages import ObjectsStage
    from test_slow_movers import _pair

    world = np.concatenate([_car(5.0), _car(-20.0, y0=-6.0, length=40.0, step=0.2)])  # the car, a wall
    poses = [_translation(float(i)) for i in range(12)]
    frames = [Frame(index=i, timestamp=DT * i, points=world - [float(i), 0.0, 0.0]) for i in range(12)]
    config = SsfConfig()
    config.objects.occupied_release_share = 0.8
    stage = ObjectsStage(config)
    released = []
    for k in range(1, 12):
        state = _pair(frames, poses, k, min(k, 4))  # measured at the true pose: 1 m per scan
        source = state.prev.points
        is_car = np.arange(len(source)) < len(_car(5.0))
        ego_flow = -np.array([1.0, 0.0, 0.0])
        result = _result(source, is_car, ego_flow + [0.5, 0.0, 0.0])  # the ego's flow + 5 m/s
        released.append(stage._release_occupied(state, result, ScanSurface(frames[k].points), None))
        assert len(stage._surfaces) <= config.objects.occupied_to_scans + 2
    # scans 1.. are kept (scan 0 was never scan k): scan k-1 = 5 is the first with one 4 scans back
    assert released == [0] * 5 + [is_car.sum()] * 6
