"""An object that is part of a static body stays static (``ssf.objects.embedded_share``).

Real KITTI 00, scans 12-13: a parked car 2.7 m beside the ego. Its flagged points (a
subset of its lower and inner points, mixed with the rest of its body) slid 0.2 m along it
under their own ICP, while the rest of the car fits the ego motion. Built here with exact
geometry: box-shaped bodies sampled every 5 cm, scan k-1 and scan k in one frame (the ego
stands still), scan k's surface as the objects stage indexes it."""

import numpy as np

from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import ScanSurface
from flowslam.sceneflow.refinement.objects import _embedded


def _grid(lo, hi, step=0.05) -> np.ndarray:
    axes = [np.arange(a, b + 1e-9, step) if b > a else np.array([a]) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _box(lo, hi) -> np.ndarray:
    """The five faces (all but the bottom) of an axis-aligned box from ``lo`` to ``hi`` (m)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return np.unique(np.concatenate([
        _grid((x0, y0, z0), (x0, y1, z1)), _grid((x1, y0, z0), (x1, y1, z1)),
        _grid((x0, y0, z0), (x1, y0, z1)), _grid((x0, y1, z0), (x1, y1, z1)),
        _grid((x0, y0, z1), (x1, y1, z1)),
    ]).round(6), axis=0)


def _shift(dx: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = dx
    return T


CAR = _box((2.0, -4.4, -1.6), (6.4, -2.6, -0.3))  # 4.4 x 1.8 x 1.3 m, beside the ego


def _subset(n: int, share: float = 0.3) -> np.ndarray:
    """A random ``share`` of n points: flagged points mixed with the rest of their body."""
    return np.sort(np.random.default_rng(0).choice(n, int(share * n), replace=False))


def test_a_flagged_part_of_a_parked_car_that_its_icp_slid_stays_static():
    """A third of a parked car's points, slid 0.2 m along the car: the rest of the car fits
    the ego motion (fitness 1) and the slide only ~0.8 (its front and back leave scan k's
    surface): embedded, static."""
    c = ObjectRefinementConfig()
    surface = ScanSurface(CAR)
    solid = np.arange(len(CAR))
    assert _embedded(CAR, solid, CAR, _subset(len(CAR)), _shift(0.2), np.eye(4), surface, c)


def test_a_moving_car_whose_network_flagged_part_of_it_keeps_its_motion():
    """The same car driving 0.8 m along itself in scan k, a third of it flagged: its other
    points fit the object's motion, and the ego motion (sides and roof sliding along
    themselves) clearly less: not embedded."""
    c = ObjectRefinementConfig()
    surface = ScanSurface(CAR + [0.8, 0.0, 0.0])
    solid = np.arange(len(CAR))
    assert not _embedded(CAR, solid, CAR, _subset(len(CAR)), _shift(0.8), np.eye(4), surface, c)


def test_a_walker_beside_a_parked_car_is_not_embedded_in_it():
    """A walker (0.6 x 0.6 x 1.7 m box) 10 cm from the parked car's side steps 0.3 m away
    from it: only its face towards the car has car points within 15 cm, less than
    ``embedded_share`` of it, so the car beside it decides nothing. With the share test
    off, the car's side (which the walker's motion moves off scan k's surface) would make
    the walker static."""
    walker = _box((3.5, -2.5, -1.6), (4.1, -1.9, 0.1))
    scan_km1 = np.concatenate([CAR, walker])
    away = np.eye(4)
    away[1, 3] = 0.3
    surface = ScanSurface(np.concatenate([CAR, walker + away[:3, 3]]))
    mine = np.arange(len(CAR), len(scan_km1))
    solid = np.arange(len(scan_km1))
    assert not _embedded(scan_km1, solid, scan_km1, mine, away, np.eye(4), surface, ObjectRefinementConfig())
    assert _embedded(scan_km1, solid, scan_km1, mine, away, np.eye(4), surface, ObjectRefinementConfig(embedded_share=0.0))
