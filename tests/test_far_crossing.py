"""Seen-through points of a far vehicle crossing the line of sight.

At 37 m a bin of 0.4 degrees spans ~0.26 m. A car driving across the line of sight at 3.5 m/s
leaves a strip of 0.35 m in one scan: every window of 3 x 3 bins around a point of that strip
still holds the car, so none of its points is seen through; each point's own bin within the
strip sees the wall behind. Built with exact geometry (faces sampled densely enough that every
range-image bin has returns); the ego vehicle drives forward."""

import numpy as np

from flowslam import geometry
from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.sceneflow.refinement.visibility import RangeImage, geometric_movers, slow_movers
from test_slow_movers import HEIGHT, _box, _grid, _pose, _scan

CAR = (1.8, 4.4, 1.5)  # driving along y: its long side faces the sensor
CAR_X = 37.0


def _world(car_y: float) -> tuple[np.ndarray, np.ndarray]:
    """World points (world = scan k-1's sensor frame) and the car's mask: a car centred at
    (37, ``car_y``), a wall 15 m behind it, the ground."""
    car = _box((CAR_X, car_y), size=CAR)
    wall = _grid((CAR_X + 15.0, -8.0, -HEIGHT), (CAR_X + 15.0, 8.0, 1.0))
    ground = _grid((-4.0, -8.0, -HEIGHT), (CAR_X + 16.0, 8.0, -HEIGHT), step=0.25)
    points = np.concatenate([car, wall, ground])
    return points, np.arange(len(points)) < len(car)


def _pair(car_step: float):
    """(scan k-1, its car mask, scan k, T_ego = T_{k,k-1}): the car moves by ``car_step`` (m,
    along y) between the scans."""
    before, car = _world(0.0)
    after, _ = _world(car_step)
    return _scan(before, _pose(0)), car, _scan(after, _pose(1)), geometry.inv(_pose(1)) @ _pose(0)


def test_a_far_car_crossing_the_line_of_sight_is_seen_through_in_its_own_bins_only():
    window = MotionEvidenceConfig(own_bin_from_m=None)
    prev, car, target, T_ego = _pair(0.35)
    movers, seen = geometric_movers(prev, target, T_ego, window)
    assert seen[car].sum() < window.min_points and not movers.any()
    own = MotionEvidenceConfig(own_bin_from_m=30.0)
    movers, seen = geometric_movers(prev, target, T_ego, own)
    assert seen[car].sum() >= own.min_points and movers[car].sum() >= own.min_points
    assert not movers[~car].any() and not seen[~car].any()  # the wall behind it and the ground stay put
    beyond = window.model_copy(update={"own_bin_from_m": 40.0})  # the car is nearer: the window decides
    seen_beyond = geometric_movers(prev, target, T_ego, beyond)[1]
    assert np.array_equal(seen_beyond, geometric_movers(prev, target, T_ego, window)[1])


def test_a_far_parked_car_is_not_seen_through_in_its_own_bins():
    own = MotionEvidenceConfig(own_bin_from_m=30.0)
    prev, _, target, T_ego = _pair(0.0)
    movers, seen = geometric_movers(prev, target, T_ego, own)
    assert not movers.any() and not seen.any()


def _older_pair(car_shift: float):
    """(scan k-1, its car mask, the scan 7 before it, ``T_old_{k-1}``): the car stood
    ``car_shift`` (m, along y) behind its place in scan k-1 then; the ego drove 7 steps."""
    before, _ = _world(-car_shift)
    now, car = _world(0.0)
    return _scan(now, _pose(7)), car, _scan(before, _pose(0)), geometry.inv(_pose(0)) @ _pose(7)


def test_far_off_the_slow_test_looks_at_each_points_row_of_the_window():
    """The car crossed 2.4 m in 7 scans (3.5 m/s): the older scan saw the wall behind the
    front of its place now. Each point's row of the window (``baseline_row_from_m`` 30: its
    elevation bin and its azimuth neighbours) flags more of the car than the whole window,
    whose rings above and below hold the car's roof edge and the ground in front of its lowest
    points; nothing else is flagged, a parked car is not, and with the range beyond the car
    (40 m) the window decides."""
    window = MotionEvidenceConfig(baseline_row_from_m=None)
    row = window.model_copy(update={"baseline_row_from_m": 30.0})
    prev, car, old, T_old_prev = _older_pair(2.4)
    by_window = slow_movers(prev, T_old_prev, RangeImage(old, window), window)
    by_row = slow_movers(prev, T_old_prev, RangeImage(old, row), row)
    assert by_row[car].sum() > by_window[car].sum() + row.min_points
    assert not by_row[~car].any()
    beyond = window.model_copy(update={"baseline_row_from_m": 40.0})
    assert np.array_equal(slow_movers(prev, T_old_prev, RangeImage(old, beyond), beyond), by_window)
    parked, _, old_parked, T = _older_pair(0.0)
    assert not slow_movers(parked, T, RangeImage(old_parked, row), row).any()
