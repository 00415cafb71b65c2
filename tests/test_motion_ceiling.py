"""The motion tests' ceiling: points high above the local ground are not tested.

A sparse sensor's older scan sees through tree canopies where a later scan hits them, so the
slow-mover test flags them (fresh `static` 784, stop 65). Here a box floating 3 m above the
ground stands in for a canopy and moves like the walker of ``test_slow_movers`` (0.45 m in
three scans): without a ceiling both are flagged; with ``max_height_m`` 2.5 only the walker."""

import numpy as np

from flowslam import geometry
from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.sceneflow.refinement.visibility import RangeImage, slow_movers
from test_slow_movers import HEIGHT, _box, _grid, _pose, _scan

LIFT = 3.0  # the floating box's bottom above the ground (m)


def _world(y: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (world = the older scan's sensor frame) and the masks of the walker at (10, y)
    and of the floating box at (10, -y): a wall 14 m ahead, the ground."""
    wall = _grid((14.0, -4.0, -HEIGHT), (14.0, 4.0, 4.0))
    ground = _grid((-4.0, -5.0, -HEIGHT), (16.0, 5.0, -HEIGHT), step=0.25)
    walker = _box((10.0, y))
    floating = _box((10.0, -y), size=(0.4, 0.4, 1.0)) + [0.0, 0.0, LIFT]
    parts = [wall, ground, walker, floating]
    labels = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
    return np.concatenate(parts), labels == 2, labels == 3


def test_points_above_the_ceiling_are_not_slow_movers():
    old = _scan(_world(1.45)[0], _pose(0))
    now, walker, floating = _world(1.0)
    prev = _scan(now, _pose(3))
    T_old_prev = geometry.inv(_pose(0)) @ _pose(3)
    plain = MotionEvidenceConfig(max_height_m=None)
    flagged = slow_movers(prev, T_old_prev, RangeImage(old, plain), plain)
    assert flagged[walker].mean() > 0.5 and flagged[floating].mean() > 0.5
    ceiling = MotionEvidenceConfig(max_height_m=2.5)
    flagged = slow_movers(prev, T_old_prev, RangeImage(old, ceiling), ceiling)
    assert flagged[walker].mean() > 0.5
    assert not flagged[floating].any() and not flagged[~walker].any()
