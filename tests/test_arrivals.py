"""Arrivals: points of scan k where scan k-1 saw empty space.

A car driving towards the sensor hides its old place behind its new front, so scan k never
sees through where its scan k-1 points were: the seen-through test of
:func:`geometric_movers` cannot flag it. Scan k-1 saw through where its front is now, which
the arrivals test reads from scan k-1's own range image. Built with exact geometry (faces
sampled densely enough that every range-image bin has returns, no occlusion); the ego
vehicle drives forward."""

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.sceneflow.refinement.visibility import RangeImage, geometric_movers
from test_slow_movers import HEIGHT, STEP, _box, _grid, _pose, _scan
from test_slow_movers import _pair as _stage_state

CAR = (4.4, 1.8, 1.5)


def _world(car_x: float) -> tuple[np.ndarray, np.ndarray]:
    """World points (world = scan k-1's sensor frame) and the car's mask: a car centred at
    (``car_x``, 0), a wall 15 m behind it, the ground."""
    car = _box((car_x, 0.0), size=CAR)
    wall = _grid((car_x + 15.0, -6.0, -HEIGHT), (car_x + 15.0, 6.0, 1.0))
    ground = _grid((-4.0, -6.0, -HEIGHT), (car_x + 16.0, 6.0, -HEIGHT), step=0.25)
    points = np.concatenate([car, wall, ground])
    return points, np.arange(len(points)) < len(car)


def _pair(car_x: float, car_step: float):
    """(scan k-1, its car mask, scan k, T_ego = T_{k,k-1}): the car moves by ``car_step``
    (m, along x; negative: towards the sensor) between the scans."""
    before, car = _world(car_x)
    after, _ = _world(car_x + car_step)
    T_ego = geometry.inv(_pose(1)) @ _pose(0)
    return _scan(before, _pose(0)), car, _scan(after, _pose(1)), T_ego


def test_a_car_coming_towards_the_sensor_is_found_by_its_arrivals_only():
    c = MotionEvidenceConfig()
    prev, car, target, T_ego = _pair(30.0, -0.6)  # 6 m/s towards the sensor, 30 m ahead
    movers, seen = geometric_movers(prev, target, T_ego, c)
    assert not movers.any() and not seen.any()  # nothing of it is seen through: its new front hides its old place
    movers, seen = geometric_movers(prev, target, T_ego, c, source_image=RangeImage(prev, c))
    assert movers[car].sum() >= c.min_points
    assert not movers[~car].any()  # the wall behind it and the ground stay put
    assert np.array_equal(seen, movers)  # the flagged points count as seen through (shifted ICP starts)
    switched_off = c.model_copy(update={"arrivals": False})
    assert not geometric_movers(prev, target, T_ego, switched_off, source_image=RangeImage(prev, c))[0].any()


@pytest.mark.parametrize("car_step", [0.0, 0.6])
def test_no_arrivals_for_a_parked_car_or_a_car_driving_away(car_step):
    c = MotionEvidenceConfig()
    prev, car, target, T_ego = _pair(30.0, car_step)
    image = RangeImage(prev, c)
    movers, _ = geometric_movers(prev, target, T_ego, c, source_image=image)
    plain, _ = geometric_movers(prev, target, T_ego, c)
    assert np.array_equal(movers, plain)  # the arrivals add nothing: parked, or found by what it left
    if car_step == 0.0:
        assert not movers.any()


def test_arrivals_nearer_than_their_minimum_range_are_not_movers():
    c = MotionEvidenceConfig()
    prev, car, target, T_ego = _pair(30.0, -0.6)
    found = geometric_movers(prev, target, T_ego, c, source_image=RangeImage(prev, c))[0]
    assert found[car].any()
    far_limit = c.model_copy(update={"arrival_min_range_m": 35.0})  # the car's centre is 30 m away
    assert not geometric_movers(prev, target, T_ego, far_limit, source_image=RangeImage(prev, far_limit))[0].any()


def test_the_objects_stage_makes_the_arriving_car_move_with_the_image_and_surface_it_kept():
    """Three scans of the car driving towards the sensor; the network calls every point
    static. After pair (0, 1) the stage keeps scan 1's range image and surface, and pair
    (1, 2) asks them: the car moves, at its speed; with ``arrivals: false`` it stays static."""
    from flowslam.config import SsfConfig
    from flowslam.frame import Frame
    from flowslam.sceneflow.refinement.static import RefinedFlow
    from frontends.ssf_stages import ObjectsStage, PairState

    worlds = [_world(30.0 - 0.6 * i) for i in range(3)]
    frames = [Frame(index=i, timestamp=0.1 * i, points=_scan(w, _pose(i))) for i, (w, _) in enumerate(worlds)]

    def state(k: int) -> PairState:
        """The pair (k-1, k) at the true poses, its static refinement accepted, every point static."""
        s = _stage_state(frames, [_pose(i) for i in range(3)], k, 1)
        T_ego, points = s.estimate.T_curr_prev, s.prev.points
        s.refined = RefinedFlow(np.zeros((0, 3)), np.zeros((0, 3)), T_ego, True, s.frame.points)
        s.flow, s.static = geometry.rigid_flow(T_ego, points), np.ones(len(points), dtype=bool)
        return s

    def car_moves(arrivals: bool) -> tuple[float, np.ndarray]:
        config = SsfConfig()
        config.objects.motion_evidence.arrivals = arrivals
        stage = ObjectsStage(config)
        stage.run(state(1))
        assert stage._surface[0] == (1 if arrivals else None)  # scan 1 as it was scan k, kept for the arrivals
        last = state(2)
        stage.run(last)
        return (~last.static)[worlds[1][1]].mean(), last

    share, last = car_moves(True)
    assert share > 0.5
    car = worlds[1][1] & ~last.static
    ego_landing = geometry.transform_points(last.estimate.T_curr_prev, frames[1].points[car])
    speed = np.linalg.norm(frames[1].points[car] + last.flow[car] - ego_landing, axis=1) / 0.1
    assert np.median(speed) == pytest.approx(6.0, abs=0.5)
    assert not (~last.static)[~worlds[1][1]].any()
    assert car_moves(False)[0] == 0.0
