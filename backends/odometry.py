"""Backend ``odometry``: chains the relative motions, no optimisation, loops ignored.

The first scan is anchored at ``T_world_sensor = I``; scan ``k`` is
``T_world_{k-1} @ T_prev_curr``. It is the reference every optimising backend is
compared against (same measurements, no graph).
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


class OdometryBackend:
    name = "odometry"
    accepts_loops = False
    """No graph: the run builds no loop closer for this backend."""
    exports_graph = False
    """No factor graph to write (``graph.g2o`` is for graph backends)."""

    def __init__(self):
        self._poses: list[np.ndarray] = []
        self.loops_ignored = 0

    def add_odometry(self, index, T_prev_curr, covariance) -> None:
        if not self._poses:
            self._poses.append(np.eye(4))
            return
        if T_prev_curr is None:
            raise ValueError(f"scan {index}: a relative motion is required after the first scan")
        self._poses.append(self._poses[-1] @ np.asarray(T_prev_curr, dtype=np.float64))

    def add_loop(self, i, j, T_i_j, covariance) -> None:
        self.loops_ignored += 1
        log.debug("odometry backend ignores loop %d-%d", i, j)

    def latest_pose(self) -> np.ndarray:
        return self._poses[-1].copy()

    def trajectory(self) -> np.ndarray:
        return np.array(self._poses).reshape(-1, 4, 4)


def make_backend(config) -> OdometryBackend:
    return OdometryBackend()
