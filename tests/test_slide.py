"""The slide test: a car driving along its own side, told from a parked one by an older scan.

The scene of ``test_far_crossing``: a car 37 m ahead of the older scan's sensor (31.4 m at
scan k-1) whose long side faces the sensor, a wall 15 m behind it, the ground; the ego drives
forward 0.8 m per scan. The car drives along y
(its long axis) ``step`` metres per scan. The older scan is the one 7 scans before scan k-1.
"""

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config.ssf import MotionEvidenceConfig, ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import ScanSurface
from flowslam.sceneflow.refinement.objects import _principal_axis, _score
from flowslam.sceneflow.refinement.slide import OlderView, slide_motion
from flowslam.sceneflow.refinement.visibility import RangeImage
from test_far_crossing import _world
from test_slow_movers import HEIGHT, _grid, _pose, _scan

BACK = 7


def _scene(step: float, hidden_below_y: float | None = None):
    """(scan k-1, its car mask, scan k, T_ego = T_{k,k-1}, the older scan's OlderView): the car
    drives ``step`` m per scan along y; with ``hidden_below_y``, a truck stood 20 m ahead of
    the older scan's sensor then (gone since), hiding the car's lane up to about that y."""
    evidence = MotionEvidenceConfig()
    old_world, _ = _world(-BACK * step)
    if hidden_below_y is not None:
        truck = _grid((20.0, -12.0, -HEIGHT + 0.05), (20.0, hidden_below_y * 20.0 / 37.0, 1.0))
        old_world = np.concatenate([old_world, truck])
    prev_world, car = _world(0.0)
    next_world, _ = _world(step)
    old = _scan(old_world, _pose(0))
    prev, target = _scan(prev_world, _pose(BACK)), _scan(next_world, _pose(BACK + 1))
    T_ego = geometry.inv(_pose(BACK + 1)) @ _pose(BACK)
    T_old_prev = geometry.inv(_pose(0)) @ _pose(BACK)
    view = OlderView(RangeImage(old, evidence), T_old_prev, BACK, evidence)
    return prev, car, target, T_ego, view


def _slide(step: float, hidden_below_y: float | None = None, **options):
    """The slide :func:`slide_motion` finds for the car of :func:`_scene` (None: none), as
    its displacement per scan in frame k-1 beyond the ego motion (m)."""
    c = ObjectRefinementConfig(**{"slide_free_share": 0.25, **options})
    prev, car, target, T_ego, view = _scene(step, hidden_below_y)
    p = prev[car]
    surface = ScanSurface(target)
    fits = lambda M: _score(p, M, surface, c)  # noqa: E731
    T = slide_motion(p, _principal_axis(p), T_ego, view, fits, fits(T_ego)[0], c)
    return None if T is None else T_ego[:3, :3].T @ (T[:3, 3] - T_ego[:3, 3])


def test_a_car_driving_along_its_side_slides_at_its_speed():
    """0.5 m per scan: the older scan saw the wall where the car's front is now; 0.4 m per
    scan would put its front beyond where the older scan saw it, so the slowest slide both
    scans allow is the car's own."""
    shift = _slide(0.5)
    assert shift is not None
    assert shift == pytest.approx([0.0, 0.5, 0.0], abs=1e-9)


def test_a_parked_car_does_not_slide():
    """The older scan saw the car where it is: nothing to explain."""
    assert _slide(0.0) is None


def test_where_the_older_scan_saw_nothing_of_the_old_place_the_slide_is_a_lower_bound():
    """A truck hid the car's lane behind y = 0.5 m from the older scan: every slide that takes
    the car behind the truck then is allowed (its front, now at y = 2.2 m, must go back
    beyond 0.5 m: more than 0.24 m per scan), and the slowest, 0.3 m per scan, is kept --
    slower than the car, but moving."""
    shift = _slide(0.5, hidden_below_y=0.5)
    assert shift is not None
    assert shift == pytest.approx([0.0, 0.3, 0.0], abs=1e-9)


def test_a_slide_needs_its_share_of_points_in_the_older_scans_free_space():
    """Not every point of the car is in the older scan's free space (its rear stood where the
    car was): asking for all of them, no slide is tried; nor is one faster than the fastest
    tried."""
    assert _slide(0.5, slide_free_share=1.0) is None
    assert _slide(0.5, slide_max_step_m=0.45) is None


def test_a_slice_on_fewer_rings_than_slide_min_rings_does_not_slide():
    """One ring's arc across the moving car (its points within 0.1 deg of one elevation, as a
    sparse sensor sees a body 30 m off): the older scan's rings at other heights see through
    such an arc on a parked body too, so it is not slid; the whole car is, and the same arc is
    where one ring is enough (``slide_min_rings`` 1)."""
    from flowslam.sceneflow.refinement.clusters import ring_count
    from flowslam.sceneflow.refinement.objects import _plane_distances, _slid

    prev, car, target, T_ego, view = _scene(0.5)
    p = prev[car]
    elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
    arc = p[np.abs(elevation - np.median(elevation)) < 0.05]
    surface = ScanSurface(target)

    def slid(points, **options):
        c = ObjectRefinementConfig(**{"slide_free_share": 0.25, **options})
        plane = _plane_distances(geometry.transform_points(T_ego, points), surface, c)
        return _slid(points, None, plane, T_ego, view, surface, c)

    c = ObjectRefinementConfig()
    assert ring_count(arc, c.ring_gap_rad) < c.slide_min_rings <= ring_count(p, c.ring_gap_rad)
    assert len(arc) >= c.min_points
    assert slid(p) is not None
    assert slid(arc) is None
    assert slid(arc, slide_min_rings=1) is not None
