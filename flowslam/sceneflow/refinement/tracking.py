"""Mover tracking from one scan pair to the next: ``MoverPrior`` (constant object velocity).

Frames: the movers of pair (k-1, k) are stored as landing spots in sensor frame k;
``T_ego`` is ``T_{k,k-1}`` when recording and ``T_{k+1,k}`` when predicting; metres
per scan interval.
"""

from __future__ import annotations

import numpy as np

from flowslam.geometry import rigid_flow, transform_points
from flowslam.sceneflow.refinement.clusters import (
    LocalGround,
    above_ground,
    bev_extent,
    dense_grid_shape,
    grid_occupancy,
    grid_voxel_ids,
    in_bounds,
)

__all__ = ["MoverPrior", "object_evidence", "small_instances"]


class MoverPrior:
    """Carries the moving points of one scan pair over to the next (constant object velocity).

    After pair (k-1, k): the landing spots ``p + f`` (sensor frame k) of the points found
    dynamic, and each one's own motion ``m = p + f - T_{k,k-1} p`` (frame k, metres per
    scan interval). For pair (k, k+1) the points of scan k within ``radius_m`` of a
    landing spot become dynamic candidates with the predicted flow
    ``T_{k+1,k} p - p + R_{k+1,k} m`` (the ICP's start), so that an object found once
    keeps being refined even where the network misses it.

    The reach of a landing spot grows with its horizontal range ``d`` (m) from the sensor,
    as the beams' spacing does: ``clip(radius_per_m * d, radius_m, max(radius_m, max_radius_m))``
    (``radius_per_m`` 0: ``radius_m`` everywhere). A point is a candidate when it lies within
    the reach of its nearest landing spot. With ``grow_max_extent_m`` > 0 only the landing spots
    of small objects grow so: those whose instance spans at most that many metres horizontally
    (the diagonal of its points' BEV box in scan k-1); the others, and dynamic points without
    an instance, keep ``radius_m``.

    With ``max_quiet_pairs`` > 0, a mover is carried for at most that many pairs in a row in
    which it had no evidence of its own (``update``'s ``evidence``: the network's labels,
    geometric or slow-mover flags, seen-through points): each landing spot counts the pairs
    since its object last had some, and spots that reached the limit are not carried. A
    track is a prior, not evidence: a slow object's ICP from the carried start can slide a
    static bush on to the next pair as well as a walker.
    """

    def __init__(self, radius_m: float = 0.15, ground_cell_m: float = 2.0, ground_clearance_m: float = 0.25,
                 radius_per_m: float = 0.0, max_radius_m: float = 0.0, grow_max_extent_m: float = 0.0,
                 max_quiet_pairs: int = 0, quiet_min_extent_m: float = 0.0):
        self.radius_m = radius_m
        self.max_quiet_pairs, self.quiet_min_extent_m = max_quiet_pairs, quiet_min_extent_m
        self.radius_per_m, self.max_radius_m = radius_per_m, max_radius_m
        self.grow_max_extent_m = grow_max_extent_m
        self.ground_cell_m, self.ground_clearance_m = ground_cell_m, ground_clearance_m
        self._landing: np.ndarray | None = None
        self._motion: np.ndarray | None = None
        self._grows: np.ndarray | None = None
        """(M,) bool: the landing spots whose reach may grow (None: all)."""
        self._quiet: np.ndarray | None = None
        """(M,) int: the pairs in a row each landing spot's object went without evidence."""
        self._carried: tuple[int, np.ndarray] | None = None
        """(number of points, (N,) int): for the points of the last ``predict``, the quiet
        pairs of the spot each candidate was carried from, plus one (-1: not carried)."""

    def update(self, source: np.ndarray, flow: np.ndarray, dynamic: np.ndarray, T_ego: np.ndarray,
               ground: LocalGround | None = None, instance: np.ndarray | None = None,
               evidence: np.ndarray | None = None) -> None:
        """Record pair (k-1, k): source points (frame k-1), flow, labels, ``T_ego`` = T_{k,k-1}.
        Ground-level points are not carried (``ground_clearance_m`` above the lowest point of
        their ``ground_cell_m`` BEV cell): the road under a mover would carry its motion on.
        ``ground``: the :class:`LocalGround` of all of ``source`` to share (used when its cell
        is ``ground_cell_m``; else the ground of the points around the dynamic ones is built).
        ``instance``: (N,) instance ids (-1: none) for ``grow_max_extent_m`` (None: every spot may grow)
        and ``max_quiet_pairs`` (an instance's points share its quietness). ``evidence``: (N,)
        bool, the points whose instance (or, without one, themselves) showed motion this pair
        by other means than the track (None: all did)."""
        quiet = self._quietness(source, dynamic, instance, evidence) if self.max_quiet_pairs > 0 else None
        idx = np.flatnonzero(dynamic)
        if idx.size and self.ground_clearance_m > 0:
            idx = idx[self._above_ground(source, idx, ground)]
        p = source[idx]
        self._landing = p + flow[idx]
        self._motion = self._landing - transform_points(T_ego, p)
        self._quiet = None if quiet is None else quiet[idx]
        self._carried = None
        self._grows = None
        if self.grow_max_extent_m > 0 and instance is not None:
            self._grows = small_instances(source, instance, self.grow_max_extent_m)[idx]

    def _quietness(self, source: np.ndarray, dynamic: np.ndarray, instance: np.ndarray | None,
                   evidence: np.ndarray | None) -> np.ndarray:
        """(N,) int: the pairs in a row without evidence of each point's object (0 where it
        has evidence now or was not carried here). An instance takes the least quietness
        among its carried points: points it grew by were not carried but have no evidence."""
        n = len(source)
        if evidence is None:
            return np.zeros(n, dtype=np.int64)
        carried = self._carried[1] if self._carried is not None and self._carried[0] == n else np.full(n, -1)
        quiet = np.maximum(carried, 0)
        if instance is not None:
            has = np.flatnonzero((instance >= 0) & (carried >= 0))
            if has.size:  # instances without a carried point keep 0
                none = np.iinfo(np.int64).max
                least = np.full(int(instance.max()) + 1, none)
                np.minimum.at(least, instance[has], quiet[has])
                least[least == none] = 0
                mine = np.flatnonzero(instance >= 0)
                quiet[mine] = least[instance[mine]]
            if self.quiet_min_extent_m > 0:
                quiet[small_instances(source, instance, self.quiet_min_extent_m)] = 0
        quiet[np.asarray(evidence, dtype=bool) | ~np.asarray(dynamic, dtype=bool)] = 0
        return quiet

    def _above_ground(self, source: np.ndarray, idx: np.ndarray, ground: LocalGround | None) -> np.ndarray:
        """(len(idx),) bool: the points ``idx`` of ``source`` clear of the local ground."""
        if ground is not None and ground.cell == self.ground_cell_m:
            return ground.above(self.ground_clearance_m)[idx]
        near = np.hypot(source[:, 0], source[:, 1]) < np.hypot(*np.abs(source[idx, :2]).max(axis=0)) + 5.0
        above = np.zeros(len(source), dtype=bool)
        above[near] = above_ground(source[near], self.ground_cell_m, self.ground_clearance_m)
        return above[idx]

    def predict(self, points: np.ndarray, T_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) bool candidates among ``points`` (scan k, frame k) and their (N,3) predicted
        flow (rows of non-candidates are zero), given ``T_ego`` = T_{k+1,k}."""
        mask = np.zeros(len(points), dtype=bool)
        flow = np.zeros((len(points), 3))
        self._carried = None
        if self._landing is None or len(self._landing) == 0:
            return mask, flow
        idx, j = self._near_landing(points)
        if self._quiet is not None:
            keep = self._quiet[j] < self.max_quiet_pairs
            idx, j = idx[keep], j[keep]
            carried = np.full(len(points), -1)
            carried[idx] = self._quiet[j] + 1
            self._carried = (len(points), carried)
        mask[idx] = True
        p = points[idx]
        flow[idx] = rigid_flow(T_ego, p) + self._motion[j] @ T_ego[:3, :3].T
        return mask, flow

    def _near_landing(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the ``points`` within the reach of their nearest landing spot, and of that
        spot. Exact: only points in a voxel (edge: the largest reach) next to a landing spot's
        voxel can be that close, and only they search the KD-tree."""
        from scipy.spatial import cKDTree

        reach = self._reach()
        r = self.radius_m if reach is None else float(reach.max())
        lo, hi = self._landing.min(axis=0) - r, self._landing.max(axis=0) + r
        inside = np.flatnonzero(in_bounds(points, lo, hi))
        shape = dense_grid_shape(lo, hi, r) if r > 0 else None
        if shape is not None:
            grid = grid_occupancy(self._landing, lo, r, shape, dilate=True)
            inside = inside[grid[grid_voxel_ids(points[inside], lo, r, shape)]]
        dist, j = cKDTree(self._landing).query(points[inside], distance_upper_bound=r)
        hit = np.isfinite(dist)
        if reach is not None:
            hit[hit] = dist[hit] <= reach[j[hit]]
        return inside[hit], j[hit]

    def _reach(self) -> np.ndarray | None:
        """(M,) reach (m) of each landing spot, or None where it is ``radius_m`` everywhere."""
        if self.radius_per_m <= 0 or self.max_radius_m <= self.radius_m:
            return None
        d = np.hypot(self._landing[:, 0], self._landing[:, 1])
        reach = np.clip(self.radius_per_m * d, self.radius_m, self.max_radius_m)
        if self._grows is not None:
            reach[~self._grows] = self.radius_m
        return reach


def small_instances(points: np.ndarray, instance: np.ndarray, max_extent_m: float) -> np.ndarray:
    """(N,) bool: the ``points`` (N,3, any frame with z up) whose instance id (``instance``,
    (N,), -1: none) spans at most ``max_extent_m`` horizontally: the diagonal of the BEV box
    of the instance's points. Points without an instance are False."""
    out = np.zeros(len(points), dtype=bool)
    has = np.flatnonzero(instance >= 0)
    if has.size:
        ids = instance[has]
        out[has] = bev_extent(points[has, :2], ids, int(ids.max()) + 1)[ids] <= max_extent_m
    return out


def object_evidence(flags: np.ndarray, instance: np.ndarray, min_points: int, min_share: float) -> np.ndarray:
    """(N,) bool: the points whose object shows motion by its own ``flags`` ((N,) bool, e.g.
    the network's dynamic labels or free-space flags): an instance (``instance`` (N,) ids,
    -1: none) with at least ``min_points`` flagged points and ``min_share`` of its points
    flagged, all its points; a point without an instance, when it is flagged itself."""
    flags = np.asarray(flags, dtype=bool)
    out = flags & (instance < 0)
    has = np.flatnonzero(instance >= 0)
    if has.size:
        ids = instance[has]
        total = np.bincount(ids)
        flagged = np.bincount(ids, weights=flags[has], minlength=len(total))
        shown = (flagged >= min_points) & (flagged >= min_share * total)
        out[has] = shown[ids]
    return out
