"""Geometric evidence of motion between two scans, given the ego motion (no learning).

Move the points of scan ``k-1`` into sensor frame ``k`` with the ego motion. A static
point then lies on a surface of scan ``k``, or behind one (occluded). Two tests:

- **off surface**: no point of scan ``k`` within ``off_surface_m`` of it;
- **seen through** (free space): in a range image of scan ``k`` (azimuth x elevation
  bins, nearest range per bin), every bin with a return in a small window around the
  point's direction has it clearly *beyond* the point -- scan ``k`` sees through where
  the point was, so whatever was there has left. Bins without a return count as unknown,
  so the test is conservative: it fires on the trailing part of a moving object.

:func:`geometric_movers` groups the non-ground points that are off surface into BEV
connected components and keeps those that hold enough seen-through points: moving
objects found by geometry alone, which the learned segmentation may have missed. The
seen-through test fires on what an object leaves behind, so it misses an object coming
towards the sensor (its old place is hidden behind its new one). The reverse test finds
it: **arrivals**, points of scan ``k`` where a range image of scan ``k-1`` saw through --
something now stands where scan ``k-1`` saw empty space.
:func:`slow_movers` applies the free-space test against an older scan instead of scan
``k``: what moves a few centimetres per scan leaves no surface in one step, but an older
scan's free space after a few; and where the older scan saw something just in front of a
point, the place scan k-1 now sees through (a walker walking away hid its new place behind
its old body).

Frames: ``source`` in sensor frame ``k-1``, ``target`` in sensor frame ``k``,
``T_ego`` = ``T_{k,k-1}``; metres and degrees.
"""

from __future__ import annotations

import numpy as np
from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.geometry import inv, row_norms, transform_points
from flowslam.sceneflow.refinement.clusters import (
    LocalGround,
    ScanSurface,
    above_ground,
    bev_clusters,
    bev_extent,
    cluster_minimum,
    in_bounds,
)

__all__ = ["RangeImage", "baseline_window_margins", "free_in_older", "spherical", "geometric_movers", "hidden_points",
           "slow_movers"]




def spherical(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth (deg, -180..180), elevation (deg) and range (m) of (N,3) points."""
    r = row_norms(points)
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    el = np.degrees(np.arcsin(np.clip(points[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0)))
    return az, el, r


class RangeImage:
    """Nearest range per (elevation, azimuth) bin of a scan (points in its sensor frame)."""

    def __init__(self, points: np.ndarray, config: MotionEvidenceConfig | None = None):
        from scipy import ndimage

        self.config = c = config or MotionEvidenceConfig()
        az, el, r = spherical(np.asarray(points, dtype=np.float64))
        self.el0 = float(el.min()) if len(el) else 0.0
        self.n_az = int(np.ceil(360.0 / c.azimuth_resolution_deg))
        self.n_el = (int(np.ceil((float(el.max()) - self.el0) / c.elevation_resolution_deg)) + 1) if len(el) else 1
        image = np.full((self.n_el, self.n_az), np.inf)
        np.minimum.at(image, self._bins(az, el), r)
        self.nearest = image
        """Nearest return per bin (+inf: none)."""
        size = 2 * c.window + 1
        # nearest return within the window (empty bins are +inf: they do not count) ...
        self.window_min = ndimage.minimum_filter(image, size=size, mode=("nearest", "wrap"))
        # ... and whether the window has any return at all
        self.window_known = ndimage.maximum_filter(np.isfinite(image), size=size, mode=("nearest", "wrap"))
        self._row = None

    def _bins(self, az: np.ndarray, el: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        ia = np.floor((az + 180.0) / c.azimuth_resolution_deg).astype(np.int64) % self.n_az
        ie = np.floor((el - self.el0) / c.elevation_resolution_deg).astype(np.int64)
        return ie, ia

    def _lookup(self, points: np.ndarray, own_bin: bool = False, row: bool = False):
        """(range (N,), nearest return in each point's window (N,) -- in its own bin with
        ``own_bin``, in its row of the window (its elevation bin only) with ``row`` --, whether
        that window (bin, row) has any return (N,), whether the point's direction lies within
        the image's elevations (N,))."""
        az, el, r = spherical(np.asarray(points, dtype=np.float64))
        ie, ia = self._bins(az, el)
        inside = (ie >= 0) & (ie < self.n_el)
        ie = np.clip(ie, 0, self.n_el - 1)
        if own_bin:
            nearest = self.nearest[ie, ia]
            return r, nearest, np.isfinite(nearest), inside
        if row:
            row_min, row_known = self._rows()
            return r, row_min[ie, ia], row_known[ie, ia], inside
        return r, self.window_min[ie, ia], self.window_known[ie, ia], inside

    def _rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(nearest return, whether any) over each bin and its ``window`` azimuth neighbours in
        its own elevation bin; computed on first use."""
        if self._row is None:
            from scipy import ndimage

            size = (1, 2 * self.config.window + 1)
            self._row = (ndimage.minimum_filter(self.nearest, size=size, mode=("nearest", "wrap")),
                         ndimage.maximum_filter(np.isfinite(self.nearest), size=size, mode=("nearest", "wrap")))
        return self._row

    def _margins(self, margin_m, relative_margin) -> tuple:
        """(margin (m), relative margin): the given ones, the config's where None."""
        c = self.config
        return (c.margin_m if margin_m is None else margin_m,
                c.relative_margin if relative_margin is None else relative_margin)

    def in_front(self, points: np.ndarray, margin_m: float | np.ndarray | None = None,
                 relative_margin: float | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """((N,) bool: in the window around each point's direction some bin has a return
        clearly nearer than the point, by ``margin_m`` + ``relative_margin`` r (the config's
        margins unless given; scalars or (N,)) -- something of this scan stands in front of
        where the point is, which may hide it; (N,3) where that nearest return stands: on
        the point's own ray at its range, m)."""
        points = np.asarray(points, dtype=np.float64)
        margin, relative = self._margins(margin_m, relative_margin)
        r, nearest, _, inside = self._lookup(points)
        front = inside & (nearest < r - margin - relative * r)
        where = points * (np.where(front, nearest, r) / np.maximum(r, 1e-9))[:, None]
        return front, where

    def seen_at(self, points: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
        """((N,) bool: the window around each point's direction (sensor frame of this scan)
        has a return; (N,) bool: its nearest return lies within ``margin_m`` of the point's
        range -- this scan saw something where the point is, neither in front nor beyond)."""
        r, nearest, known, inside = self._lookup(points)
        known = known & inside
        return known, known & (np.abs(nearest - r) <= margin_m)

    def sees_beyond(self, points: np.ndarray, own_bin: bool = False, margin_m: float | np.ndarray | None = None,
                    relative_margin: float | np.ndarray | None = None, row: bool = False) -> np.ndarray:
        """(N,) bool: in the window around each point's direction (sensor frame of this scan)
        -- or in its own bin, with ``own_bin``, or in its row of the window (its own elevation
        bin and its azimuth neighbours), with ``row`` -- at least one bin has a return and every
        return lies clearly beyond the point: farther than r + ``margin_m`` +
        ``relative_margin`` r (the config's margins unless given; scalars or (N,))."""
        margin, relative = self._margins(margin_m, relative_margin)
        r, nearest, known, inside = self._lookup(points, own_bin, row)
        return inside & known & (nearest > r + margin + relative * r)


def geometric_movers(
    source: np.ndarray,
    target: np.ndarray,
    T_ego: np.ndarray,
    config: MotionEvidenceConfig | None = None,
    surface: ScanSurface | None = None,
    ground: LocalGround | None = None,
    range_image: RangeImage | None = None,
    source_image: RangeImage | None = None,
    source_surface: ScanSurface | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(movers, seen_through): (N,) bool masks over ``source`` (module doc).

    ``surface``: a :class:`ScanSurface` of ``target`` to share (it must hold every target
    point within ``max_range_m + off_surface_m`` of the sensor, horizontally, plus the ego
    motion); ``ground``: the :class:`LocalGround` of all of ``source`` (with a cell of
    ``ground_cell_m``) to share; ``range_image``: the :class:`RangeImage` of ``target``
    with ``config``. Each is built here when not given. ``source_image``: the
    :class:`RangeImage` of ``source`` itself; with it and ``arrivals``, the off-surface
    clusters that scan k's arrivals confirm are movers too, and their off-surface points
    count as seen through (:func:`_arrivals`, :func:`_arrival_clusters`;
    ``source_surface``: a :class:`ScanSurface` of ``source`` to share, built locally when
    not given)."""
    c = config or MotionEvidenceConfig()
    movers = np.zeros(len(source), dtype=bool)
    seen = np.zeros(len(source), dtype=bool)
    near = _tested(source, c, ground)
    if near.size == 0:
        return movers, seen
    x = transform_points(T_ego, source[near])
    if surface is None:
        surface = ScanSurface(target, c.max_range_m + 5.0)
    off = ~surface.near_any(x, c.off_surface_m)
    near, x = near[off], x[off]
    if near.size == 0:
        return movers, seen
    range_image = range_image or RangeImage(target, c)
    seen[near] = range_image.sees_beyond(x)
    if c.own_bin_from_m is not None:
        far = np.flatnonzero(np.hypot(x[:, 0], x[:, 1]) >= c.own_bin_from_m)
        seen[near[far]] = range_image.sees_beyond(x[far], own_bin=True)
    movers = _compact_clusters(source, near, c, seen[near])
    if c.arrivals and source_image is not None:
        seeds = _compact_clusters(source, near, c)[near]  # only clusters big enough may take arrivals
        arrived = _arrivals(source, x[seeds], surface, T_ego, source_image, c, source_surface)
        arrived = _arrival_clusters(source, near, arrived, c)
        movers |= arrived
        seen |= arrived
    return movers, seen


def _arrivals(source: np.ndarray, landings: np.ndarray, surface: ScanSurface, T_ego: np.ndarray,
              source_image: RangeImage, c: MotionEvidenceConfig, source_surface: ScanSurface | None = None) -> np.ndarray:
    """(M,3) the points of scan k (``surface``) that arrived, in frame k-1: near an
    off-surface point's ego landing ``landings`` (frame k; those of the off-surface
    clusters that are big enough to be movers; :meth:`ScanSurface.around`, the
    surface's BEV buckets) at least ``arrival_min_range_m`` - ``bucket_m`` from the
    sensor, where scan k-1's image ``source_image`` sees beyond them both in the
    seen-through test's window and in their own bin (margins
    ``arrival_margin_m`` + ``arrival_relative_margin`` r), and with no point of scan k-1
    within ``off_surface_m`` (``source_surface``: a :class:`ScanSurface` of ``source`` to
    ask, e.g. kept from when it was scan k; else one of the points of ``source`` around
    the arrivals). The own bin keeps a sparse sensor's gaps between rings from counting as
    free space; the last test keeps what scan k-1 saw through glass or beside an edge, but
    did see, from counting as arrived."""
    far = np.hypot(landings[:, 0], landings[:, 1]) >= c.arrival_min_range_m - surface.bucket_m
    y = transform_points(inv(T_ego), surface.points[surface.around(landings[far, :2])])
    margins = {"margin_m": c.arrival_margin_m, "relative_margin": c.arrival_relative_margin}
    y = y[source_image.sees_beyond(y, **margins)]
    y = y[source_image.sees_beyond(y, own_bin=True, **margins)]
    if len(y) == 0:
        return y
    pad = c.off_surface_m
    if source_surface is None:
        source_surface = ScanSurface(source[in_bounds(source, y.min(axis=0) - pad, y.max(axis=0) + pad)])
    if len(source_surface) == 0:
        return y
    return y[~np.isfinite(source_surface.nearest(y, pad)[0])]


def _arrival_clusters(source: np.ndarray, near: np.ndarray, arrived: np.ndarray, c: MotionEvidenceConfig) -> np.ndarray:
    """(N,) bool over ``source``: the off-surface points ``near`` (indices) of the BEV
    clusters (``cluster_cell_m``) of them and the ``arrived`` points (frame k-1) that hold
    at least ``min_points`` of them and ``min_seen_through`` arrivals, at most
    ``max_extent_m`` across, whose centre (of all their points) lies at least
    ``arrival_min_range_m`` from the sensor (horizontally)."""
    flagged = np.zeros(len(source), dtype=bool)
    if near.size == 0 or len(arrived) == 0:
        return flagged
    xy = np.concatenate([source[near, :2], arrived[:, :2]])
    labels = bev_clusters(xy, c.cluster_cell_m)
    n = int(labels.max()) + 1
    own, total = labels[:near.size], np.bincount(labels, minlength=n)
    centre = np.stack([np.bincount(labels, weights=xy[:, i], minlength=n) for i in (0, 1)], axis=1) / total[:, None]
    kept = ((np.bincount(own, minlength=n) >= c.min_points)
            & (np.bincount(labels[near.size:], minlength=n) >= c.min_seen_through)
            & (bev_extent(xy, labels, n) <= c.max_extent_m)
            & (np.hypot(centre[:, 0], centre[:, 1]) >= c.arrival_min_range_m))
    flagged[near[kept[own]]] = True
    return flagged


def slow_movers(
    source: np.ndarray,
    T_old_source: np.ndarray,
    old_image: RangeImage,
    config: MotionEvidenceConfig | None = None,
    ground: LocalGround | None = None,
    source_image: RangeImage | None = None,
    min_range_m: float = 0.0,
) -> np.ndarray:
    """(N,) bool over ``source`` (scan k-1): points of BEV clusters of at least ``min_points``
    non-ground points (within ``max_range_m`` and at least ``min_range_m``, horizontally;
    extent at most ``max_extent_m``) where an older scan sees through them.
    ``T_old_source`` maps ``source`` into that scan's sensor frame (the frontend's own
    poses); ``old_image``: its :class:`RangeImage` with ``config``.

    Free space in the older scan where a point of scan k-1 is now means that something
    arrived there since: an object moving too slowly to leave scan k's surface in one step
    (the off-surface test of :func:`geometric_movers`) has left the older scan's free space
    after a few. Only these points are flagged (not seen-through): they become candidates,
    and their own ICP decides (``ground``: as in :func:`geometric_movers`). The free-space
    test is the seen-through one (a window of bins, its margins); with ``baseline_own_bin``
    it looks at each point's own bin with the margins ``baseline_margin_m`` +
    ``baseline_relative_margin`` r instead: a walker shifts by less than a window in a few
    scans, so more slow walkers are found, and more static objects (opt-in).

    ``source_image``: the :class:`RangeImage` of ``source`` itself. With it and
    ``baseline_vacated``, a point is also flagged where the older scan saw something at most
    ``baseline_vacated_max_m`` in front of it (:meth:`RangeImage.in_front`) whose place on
    the point's ray ``source`` sees through: a walker walking away from the sensor hid its
    own new place behind its old body, and that body has left."""
    c = config or MotionEvidenceConfig()
    near, x = _tested_in_older(source, T_old_source, c, ground, min_range_m)
    if c.baseline_own_bin:
        free = old_image.sees_beyond(x, own_bin=True, margin_m=c.baseline_margin_m,
                                     relative_margin=c.baseline_relative_margin)
    else:
        free = free_in_older(old_image, x, c)
    if c.baseline_vacated and source_image is not None:
        margin, relative = _vacated_margins(x, c)
        front, where = old_image.in_front(x, margin, relative)
        # only just behind what left: farther behind is what its leaving revealed
        front &= row_norms(x - where) <= c.baseline_vacated_max_m
        ask = np.flatnonzero(front & ~free)
        if ask.size:
            free[ask] = source_image.sees_beyond(transform_points(inv(T_old_source), where[ask]),
                                                 margin_m=_pick(margin, ask), relative_margin=_pick(relative, ask))
    return _compact_clusters(source, near[free], c)


def free_in_older(old_image: RangeImage, x: np.ndarray, c: MotionEvidenceConfig) -> np.ndarray:
    """(N,) bool: the older scan (``old_image``) saw through the points ``x`` (N,3, its sensor
    frame, m): the seen-through test's window with :func:`baseline_window_margins`, and beyond
    ``baseline_row_from_m`` (horizontal range) each point's row of the window -- the free-space
    test of :func:`slow_movers` (without ``baseline_own_bin``)."""
    margin, relative = baseline_window_margins(c)
    free = old_image.sees_beyond(x, margin_m=margin, relative_margin=relative)
    if c.baseline_row_from_m is not None:  # far off, each point's row of the window
        far = np.flatnonzero(np.hypot(x[:, 0], x[:, 1]) >= c.baseline_row_from_m)
        free[far] = old_image.sees_beyond(x[far], row=True, margin_m=margin, relative_margin=relative)
    return free


def hidden_points(source: np.ndarray, T_old_source: np.ndarray, old_image: RangeImage,
                  config: MotionEvidenceConfig | None = None, ground: LocalGround | None = None) -> np.ndarray:
    """(N,) bool over ``source`` (scan k-1): the points :func:`slow_movers` tests that the older
    scan (``T_old_source``, ``old_image`` as there) did not see, because something stood more
    than ``baseline_vacated_max_m`` in front of them in its window (the windowed test's
    margins): from that scan's viewpoint, metres behind, a walker was hidden by what it
    walked past, and the older scan says nothing about whether it moved."""
    c = config or MotionEvidenceConfig()
    near, x = _tested_in_older(source, T_old_source, c, ground)
    margin, relative = baseline_window_margins(c)
    front, where = old_image.in_front(x, margin, relative)
    hidden = np.zeros(len(source), dtype=bool)
    hidden[near[front & (row_norms(x - where) > c.baseline_vacated_max_m)]] = True
    return hidden


def baseline_window_margins(c: MotionEvidenceConfig) -> tuple[float, float]:
    """(margin (m), relative margin) of the windowed free-space test against an older scan
    (slow movers, held tracks): ``baseline_window_margin_m`` and
    ``baseline_window_relative_margin``, the seen-through test's where None."""
    return (c.margin_m if c.baseline_window_margin_m is None else c.baseline_window_margin_m,
            c.relative_margin if c.baseline_window_relative_margin is None else c.baseline_window_relative_margin)


def _vacated_margins(x: np.ndarray, c: MotionEvidenceConfig) -> tuple:
    """(margin (m), relative margin) of the vacated test for the points ``x`` (the older
    scan's frame): the seen-through test's (None: the config's), or per point (N,) the
    windowed test's beyond ``baseline_vacated_window_from_m``."""
    if c.baseline_vacated_window_from_m is None:
        return None, None
    far = row_norms(x) >= c.baseline_vacated_window_from_m
    window_margin, window_relative = baseline_window_margins(c)
    return np.where(far, window_margin, c.margin_m), np.where(far, window_relative, c.relative_margin)


def _pick(margin, idx: np.ndarray):
    """``margin`` (None, a scalar or per point) at the points ``idx``."""
    return margin[idx] if isinstance(margin, np.ndarray) else margin


def _tested(source: np.ndarray, c: MotionEvidenceConfig, ground: LocalGround | None) -> np.ndarray:
    """Indices of the points of ``source`` that both tests look at: within ``max_range_m``
    (horizontal), clear of the local ground and, with ``max_height_m``, at most that high
    above it (``ground``: see :func:`_above_ground`)."""
    near = np.flatnonzero(np.einsum("ij,ij->i", source[:, :2], source[:, :2]) < c.max_range_m ** 2)
    near = near[_above_ground(source, near, c, ground)]
    if c.max_height_m is not None:  # the whole scan's ground: ``near`` holds no ground points any more
        if ground is None or ground.cell != c.ground_cell_m:
            ground = LocalGround(source, c.ground_cell_m)
        near = near[~ground.above(c.max_height_m)[near]]
    return near


def _tested_in_older(source: np.ndarray, T_old_source: np.ndarray, c: MotionEvidenceConfig,
                     ground: LocalGround | None, min_range_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The points of ``source`` an older scan is asked about (:func:`slow_movers`,
    :func:`hidden_points`): their indices (:func:`_tested`, at ``min_range_m`` or farther,
    horizontally) and their positions in that scan's sensor frame (``T_old_source``)."""
    near = _tested(source, c, ground)
    if min_range_m > 0:
        near = near[np.einsum("ij,ij->i", source[near, :2], source[near, :2]) >= min_range_m ** 2]
    return near, transform_points(T_old_source, source[near])


def _compact_clusters(source: np.ndarray, idx: np.ndarray, c: MotionEvidenceConfig,
                      seen: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool over ``source``: the points ``idx`` that lie in BEV clusters of them
    (``cluster_cell_m``) of at least ``min_points`` points (``min_points_far`` from
    ``far_from_m`` on: :func:`~flowslam.sceneflow.refinement.clusters.cluster_minimum`), at most
    ``max_extent_m`` across, and -- with ``seen`` ((len(idx),) bool) -- holding at least ``min_seen_through`` seen
    points."""
    flagged = np.zeros(len(source), dtype=bool)
    if idx.size == 0:
        return flagged
    labels = bev_clusters(source[idx], c.cluster_cell_m)
    counts = np.bincount(labels)
    xy = source[idx, :2]
    kept = counts >= cluster_minimum(xy, labels, counts, c.min_points, c.min_points_far, c.far_from_m)
    if seen is not None:
        kept &= np.bincount(labels, weights=seen.astype(np.float64), minlength=len(counts)) >= c.min_seen_through
    kept[kept] = bev_extent(xy, labels, len(counts))[kept] <= c.max_extent_m
    flagged[idx[kept[labels]]] = True
    return flagged


def _above_ground(source: np.ndarray, idx: np.ndarray, c: MotionEvidenceConfig, ground: LocalGround | None) -> np.ndarray:
    """(len(idx),) bool: the points ``idx`` of ``source`` clear of the local ground. With the
    shared ``ground`` of the whole scan when its cell matches, else on ``source[idx]`` alone."""
    if ground is not None and ground.cell == c.ground_cell_m:
        return ground.above(c.ground_clearance_m)[idx]
    return above_ground(source[idx], c.ground_cell_m, c.ground_clearance_m)
