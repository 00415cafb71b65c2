"""A tracked walker beside a wall that one scan pair cannot tell from the wall keeps moving
when an older scan saw through where it is now (``objects.hold_tracks``), and a tracked
mover without evidence of its own that an older scan saw in place becomes static
(``objects.release_seen_share``); real SciPy KD-trees and range images, no network.
Frames: the sensor stands still, so every scan's sensor frame is the world frame; metres,
seconds."""

import numpy as np

from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import ScanSurface
from flowslam.sceneflow.refinement.objects import ObjectRefinement, hold_tracks, release_tracks
from flowslam.sceneflow.refinement.visibility import RangeImage

DT = 0.1
STEP = 0.1  # the walker's motion per scan along x (1 m/s)
SPACING = 0.03


def _face(x0: float, x1: float, y: float, z0: float = -1.7, z1: float = 0.0) -> np.ndarray:
    """Points on the vertical face x0..x1 at y (a grid, SPACING apart)."""
    x, z = np.meshgrid(np.arange(x0, x1, SPACING), np.arange(z0, z1, SPACING))
    return np.stack([x.ravel(), np.full(x.size, y), z.ravel()], axis=1)


WALL = _face(-5.0, 5.0, 11.0, z1=1.0)


def _walker(x: float) -> np.ndarray:
    """The face a walker 0.5 m wide shows the sensor, 10 m away, 1 m in front of the wall."""
    return _face(x, x + 0.5, 10.0)


def _hold(older_scan: np.ndarray, **options):
    """hold_tracks on scan k-1 = wall + walker at x 0, scan k = the walker STEP further,
    ``older_scan`` as the scan ``baseline_scans`` back; the walker is tracked with its motion
    and the pair's tests left everything static. Returns (held points, result, walker mask)."""
    c = ObjectRefinementConfig(**options)
    walker = _walker(0.0)
    source = np.concatenate([WALL, walker])
    target = np.concatenate([WALL, _walker(STEP)])
    tracked = np.arange(len(source)) >= len(WALL)
    tracked_flow = np.where(tracked[:, None], [STEP, 0.0, 0.0], 0.0)
    result = ObjectRefinement(np.zeros_like(source), np.zeros(len(source), bool), np.full(len(source), -1))
    older = (RangeImage(older_scan, c.motion_evidence), np.eye(4))
    held = hold_tracks(source, result, tracked, tracked_flow, np.eye(4), DT, ScanSurface(target), older, c)
    return held, result, tracked


def test_a_tracked_walker_the_older_scan_saw_through_keeps_moving():
    # seven scans back the walker stood 0.7 m to the left: where it is now, that scan saw the wall
    held, result, walker = _hold(np.concatenate([WALL, _walker(-7 * STEP)]))
    assert held == walker.sum()
    assert result.dynamic[walker].all() and not result.dynamic[~walker].any()
    assert np.allclose(result.flow[walker], [STEP, 0.0, 0.0])
    assert len(result.objects) == 1 and result.objects[0]["held"]
    assert abs(result.objects[0]["speed_mps"] - STEP / DT) < 1e-9
    assert np.all(result.instance[walker] == 0)


def test_a_track_is_not_held_where_the_older_scan_saw_it_in_place_or_saw_nothing():
    # the older scan saw the walker where it is now: it has not moved over the baseline
    assert _hold(np.concatenate([WALL, _walker(0.0)]))[0] == 0
    # the older scan saw something in front (a parked van 5 m away): nothing is known
    van = _face(-1.0, 1.5, 5.0, z1=1.0)
    assert _hold(np.concatenate([WALL, van]))[0] == 0
    # and the option off holds nothing
    assert _hold(np.concatenate([WALL, _walker(-7 * STEP)]), hold_tracks=False)[0] == 0


def test_a_track_is_not_held_when_scan_k_contradicts_its_prediction():
    """Scan k shows the walker where it was (it stopped): the prediction lands it off
    every surface of scan k, which the ego motion explains."""
    c = ObjectRefinementConfig()
    walker = _walker(0.0)
    source = np.concatenate([WALL, walker])
    target = np.concatenate([WALL, walker + [0.0, 0.0, 0.0]])
    tracked = np.arange(len(source)) >= len(WALL)
    flow = np.where(tracked[:, None], [0.0, -0.6, 0.0], 0.0)  # predicted 6 m/s towards the sensor
    result = ObjectRefinement(np.zeros_like(source), np.zeros(len(source), bool), np.full(len(source), -1))
    older = (RangeImage(np.concatenate([WALL, _walker(-7 * STEP)]), c.motion_evidence), np.eye(4))
    assert hold_tracks(source, result, tracked, flow, np.eye(4), DT, ScanSurface(target), older, c) == 0
    assert not result.dynamic.any()


def _release(older_scan: np.ndarray | None, span_s: float = 7 * DT, shown: bool = False, carried: bool | None = True,
             **options):
    """release_tracks on scan k-1 = wall + walker at x 0, where the pair's refinement moved the
    tracked walker (instance 0, STEP per scan) and left the wall static; ``older_scan``: the scan
    ``span_s`` before scan k-1 (None: no older scan); ``shown``: the walker showed motion of its
    own this pair; ``carried``: whether the track carried it (None: every instance is asked).
    Returns (released points, result, walker mask)."""
    c = ObjectRefinementConfig(**options)
    walker = _walker(0.0)
    source = np.concatenate([WALL, walker])
    tracked = np.arange(len(source)) >= len(WALL)
    result = ObjectRefinement(np.where(tracked[:, None], [STEP, 0.0, 0.0], 0.0), tracked.copy(),
                              np.where(tracked, 0, -1), [{"points": int(tracked.sum()), "accepted": True,
                                                          "speed_mps": STEP / DT}])
    older = None if older_scan is None else (RangeImage(older_scan, c.motion_evidence), np.eye(4))
    asked = None if carried is None else tracked & carried
    released = release_tracks(source, result, asked, tracked & shown, np.eye(4), older, span_s, c)
    return released, result, tracked


def test_a_tracked_mover_the_older_scan_saw_in_place_becomes_static():
    # seven scans back the "walker" stood where it is now: a static body the ICP slid along
    released, result, walker = _release(np.concatenate([WALL, _walker(0.0)]))
    assert released == walker.sum()
    assert not result.dynamic.any() and np.all(result.instance == -1)
    assert np.allclose(result.flow, 0.0)  # the ego-rigid flow of a sensor standing still
    record = result.objects[0]
    assert record["released"] and not record["accepted"] and record["seen_in_place"] == 1.0


def test_a_tracked_mover_is_kept_where_the_older_scan_saw_other_things_or_cannot_tell():
    # the walker came from 0.7 m to the left: where it is now, that scan saw the wall behind
    assert _release(np.concatenate([WALL, _walker(-7 * STEP)]))[0] == 0
    # the older scan saw nothing around it (a face far off to the side): nothing is known
    assert _release(_face(-5.0, 5.0, -11.0))[0] == 0
    assert _release(_face(-5.0, 5.0, -11.0), release_min_known=0.0)[0] == 0
    # evidence of its own this pair, a motion too short since the older scan to tell, no
    # older scan, or the option off: kept
    in_place = np.concatenate([WALL, _walker(0.0)])
    assert _release(in_place, shown=True)[0] == 0
    assert _release(in_place, span_s=2 * DT)[0] == 0
    assert _release(None)[0] == 0
    released, result, walker = _release(in_place, release_seen_share=0.0)
    assert released == 0 and result.dynamic[walker].all() and np.all(result.instance[walker] == 0)


def test_an_untracked_mover_seen_in_place_is_released_only_when_every_instance_is_asked():
    in_place = np.concatenate([WALL, _walker(0.0)])
    assert _release(in_place, carried=False)[0] == 0
    released, result, walker = _release(in_place, carried=None)
    assert released == walker.sum() and not result.dynamic.any()
