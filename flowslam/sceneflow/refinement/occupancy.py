"""Moving instances that stand where several older scans saw something: static after all.

A sparse sensor's rings hit a parked car, a fence or a bush at other heights from each
viewpoint. One pair's ICP can then move such a body into a fit of scan k as good as the ego
motion's or better, and the free-space tests fire at its edges, where a ring that hit the
body from scan k-1's viewpoint passes over it from scan k's. Several older scans together
sample the body far more densely than any one of them: the ego moved between them, so
their rings crossed it at many heights. Where nearly all the points of an instance (clear
of the ground) lie within ``occupied_radius_m`` (0.2 m) of points those older scans saw,
placed with the frontend's own poses, something stood there then. A body that moves as fast as its flow
says would have been elsewhere: at least ``release_min_shift_m`` away when the newest of
those scans was taken. The older scans must also prefer that place to the one the motion
gives: a vehicle driving along its own side stands on the line where they saw its side, and
so does its place moved back by its motion, where they saw it too. Walker-sized instances
are not asked: in a crowd one walker steps where another stood.

Frames: the instance points in sensor frame k-1 (m); each older scan's surface in its own
sensor frame, with ``T_old_prev`` mapping frame k-1 into it; seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowslam.config.ssf import ObjectRefinementConfig
from flowslam.geometry import rigid_flow, transform_points
from flowslam.sceneflow.refinement.clusters import ScanSurface
from flowslam.sceneflow.refinement.objects import PERSON_MAX_EXTENT_M, release_instance

__all__ = ["OlderSurface", "occupied_share", "release_occupied"]


@dataclass(frozen=True)
class OlderSurface:
    """An older scan for :func:`occupied_share`: its :class:`ScanSurface` (its own sensor
    frame), ``T_old_prev`` (4,4: scan k-1's sensor frame into that scan's, from the
    frontend's own poses) and how many scans before scan k-1 it was taken (>= 1)."""

    surface: ScanSurface
    T_old_prev: np.ndarray
    scans_back: int


def occupied_share(points: np.ndarray, olders: list[OlderSurface], radius_m: float,
                   step: np.ndarray | None = None) -> float:
    """Share of ``points`` ((M,3), sensor frame k-1, M >= 1) that lie within ``radius_m`` (m)
    of a point of at least one of the ``olders`` scans; with ``step`` (3,), a displacement per
    scan (frame k-1, m), each older scan is asked about the points moved back by ``step`` times
    its ``scans_back``: where a body moving by ``step`` stood then."""
    there = np.zeros(len(points), dtype=bool)
    for old in olders:
        todo = np.flatnonzero(~there)
        if todo.size == 0:
            break
        then = points[todo] if step is None else points[todo] - old.scans_back * np.asarray(step)
        dist, _ = old.surface.nearest(transform_points(old.T_old_prev, then), radius_m)
        there[todo[np.isfinite(dist)]] = True
    return float(there.mean())


def release_occupied(source: np.ndarray, result, solid: np.ndarray | None, T_ego: np.ndarray, interval: float,
                     olders: list[OlderSurface], c: ObjectRefinementConfig) -> int:
    """Moving instances that the ``olders`` scans saw in place become static
    (``occupied_release_share`` in the config: the conditions). ``source``: scan k-1 (frame
    k-1); ``result``: its :class:`~flowslam.sceneflow.refinement.objects.ObjectRefinement`,
    updated in place (a released instance's points get the ego-rigid flow of ``T_ego`` =
    ``T_{k,k-1}``, no instance, and its record ``accepted: False``, ``released: True`` and
    ``occupied_share``); ``solid`` (N,) bool: the points clear of the ground (None: all);
    ``interval``: the scan interval (s). An instance is asked when its moving points are
    wider than ``PERSON_MAX_EXTENT_M`` (BEV diagonal, m), at least 5 of them are clear of the
    ground, and their mean horizontal departure from the ego motion's flow would have moved
    them ``release_min_shift_m`` since the newest of the ``olders``; it is released when at
    least ``occupied_release_share`` of those points are :func:`occupied_share` in place, and
    that share exceeds the share moved back by that departure per scan (``moved_share`` in
    its record) by at least ``occupied_motion_margin``. Returns the number of points
    released."""
    if c.occupied_release_share <= 0 or not olders:
        return 0
    since_s = min(old.scans_back for old in olders) * interval
    released = 0
    for j in np.unique(result.instance[result.dynamic & (result.instance >= 0)]):
        idx = np.flatnonzero(result.instance == j)
        moving = idx[result.dynamic[idx]]
        if np.hypot(*np.ptp(source[moving, :2], axis=0)) <= PERSON_MAX_EXTENT_M:
            continue
        departure = np.zeros(3)  # per scan, frame k
        departure[:2] = (result.flow[moving, :2] - rigid_flow(T_ego, source[moving])[:, :2]).mean(axis=0)
        if float(np.linalg.norm(departure)) / interval * since_s < c.release_min_shift_m:
            continue
        body = moving if solid is None else moving[solid[moving]]
        if len(body) < 5:
            continue
        share = occupied_share(source[body], olders, c.occupied_radius_m)
        if share < c.occupied_release_share:
            continue
        moved = occupied_share(source[body], olders, c.occupied_radius_m, T_ego[:3, :3].T @ departure)
        if share < moved + c.occupied_motion_margin:
            continue
        released += release_instance(source, result, j, idx, T_ego, occupied_share=share, moved_share=moved)
    return released
