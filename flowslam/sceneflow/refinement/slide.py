"""Motion of an object that slides along its own side, told by an older scan's free space.

A vehicle driving along its own long axis, seen from the side (crossing the line of sight),
lands on its own side wherever it moves along it: scan k fits the ego motion about as well
as the true motion (its ends, a few percent of its points, are all that differ), so its ICP
keeps it static. An older scan, ``n`` scans back, tells them apart: under the ego motion the
older scan saw free space where much of the vehicle is now (the slow-mover test's flags),
while under its true motion the vehicle stood ``n`` displacements back, where the older scan
saw it or something in front of it, not through it.

:func:`slide_motion` tries per-scan displacements along the object's principal horizontal
axis, smallest first, and keeps the first that leaves (almost) none of the object's points
in the older scan's free space and fits scan k about as well as the ego motion: the slowest
motion both scans allow. Its speed is a lower bound where the older scan saw nothing of the
object's old place (it was hidden): every faster slide is free-space consistent too.

Frames: the object's points in sensor frame k-1 (m); ``T_ego`` = ``T_{k,k-1}``; the older
view's transform maps frame k-1 into the older scan's sensor frame.
"""

from __future__ import annotations

import numpy as np

from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.geometry import transform_points
from flowslam.sceneflow.refinement.visibility import free_in_older

__all__ = ["OlderView", "slide_motion"]


class OlderView:
    """An older scan's free space for the slide test: its range image (a
    :class:`~flowslam.sceneflow.refinement.visibility.RangeImage`), ``T_old_prev`` (4,4: scan
    k-1's sensor frame into the older scan's, from the frontend's own poses), how many scans
    before scan k-1 it was taken (``scans_back`` >= 1), and the motion-evidence config whose
    free-space test it asks, as the slow-mover test does
    (:func:`~flowslam.sceneflow.refinement.visibility.free_in_older`)."""

    def __init__(self, image, T_old_prev: np.ndarray, scans_back: int, evidence: MotionEvidenceConfig):
        self.image, self.T_old_prev, self.scans_back, self.evidence = image, T_old_prev, int(scans_back), evidence

    def free(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the older scan saw through ``points`` (frame k-1, m)."""
        return free_in_older(self.image, transform_points(self.T_old_prev, points), self.evidence)


def slide_motion(p: np.ndarray, axis: np.ndarray, T_ego: np.ndarray, older: OlderView, fits, static_fitness: float,
                 c) -> np.ndarray | None:
    """The slowest slide of an object that the older scan and scan k both allow, as a motion
    ``T_{k,k-1}`` (4,4), or None.

    ``p`` (M,3): the object's points clear of the ground (frame k-1); ``axis``: its unit
    principal horizontal axis (frame k-1); ``fits(T)``: (fitness, inlier RMSE (m)) of the
    object under the motion T against scan k; ``static_fitness``: its fitness under the ego
    motion ``T_ego`` (``fits(T_ego)[0]``, as the caller already knows it); ``c``: the objects config
    (``slide_free_share``, ``slide_max_free_share``, ``slide_step_m``, ``slide_max_step_m``,
    ``min_seen_through``, ``min_fitness``, ``max_rmse_m``, ``static_preference``).

    Runs only when the older scan saw through at least ``slide_free_share`` of ``p`` (and
    ``min_seen_through`` points) where they are now. A displacement d per scan (multiples
    of ``slide_step_m`` up to ``slide_max_step_m``, both directions along ``axis``, the
    smaller first; at equal size the one with fewer free points first) is kept when at most
    ``slide_max_free_share`` of ``p`` moved back by ``scans_back`` d lie in the older scan's
    free space, and scan k fits the object moved by d (then by the ego motion) with at least
    ``min_fitness``, within ``static_preference`` of ``static_fitness``, and an RMSE of at most
    ``max_rmse_m``."""
    if len(p) == 0:
        return None
    free_now = int(np.count_nonzero(older.free(p)))
    if free_now < max(c.min_seen_through, c.slide_free_share * len(p)):
        return None
    n = older.scans_back
    steps = np.arange(1, int(np.floor(c.slide_max_step_m / c.slide_step_m + 1e-9)) + 1) * c.slide_step_m
    for d in steps:
        tries = []
        for sign in (1.0, -1.0):
            shift = sign * d * axis
            free = int(np.count_nonzero(older.free(p - n * shift)))
            if free <= c.slide_max_free_share * len(p):
                tries.append((free, shift))
        for _, shift in sorted(tries, key=lambda t: t[0]):
            T = T_ego.copy()
            T[:3, 3] += T_ego[:3, :3] @ shift
            fitness, rmse = fits(T)
            if (fitness >= c.min_fitness and fitness + c.static_preference >= static_fitness
                    and rmse <= c.max_rmse_m):
                return T
    return None
