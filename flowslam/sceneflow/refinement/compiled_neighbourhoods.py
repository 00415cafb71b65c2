"""Covariances and normals of point neighbourhoods from a KD-tree query's result, compiled (numba).

:func:`flowslam.sceneflow.refinement.clusters.neighbourhood_covariances` asks SciPy's
KD-tree for up to k neighbours of each point; gathering them and summing their outer
products with NumPy builds (N, k, 3) temporaries and a batched product of tiny matrices,
which took more time than the query. Here each neighbourhood is summed in one pass.

:func:`neighbourhood_normals` goes on to each neighbourhood's tangent-plane normal with the
closed forms of :mod:`flowslam.sceneflow.refinement.symmetric3` (smallest eigenvalue of
the characteristic cubic, eigenvector as the longest cross product of two rows), one
neighbourhood at a time: the objects stage asks for the normals of a few dozen points at
a time, where the ~20 NumPy calls of those closed forms cost more than the arithmetic.

:func:`box_points` gathers the points inside a box from a BEV bucket index (the objects'
ICP target boxes, ~18 per KITTI pair): one pass over the buckets the box covers, where the
NumPy form concatenated, sorted, masked and sorted again.

:func:`near_any_points` answers "is some scan point within r of each query?" from a hash
table of r-sized cubes (:mod:`flowslam.compiled_hash`): the off-surface test of the geometric movers asks it for ~50k
points per scan pair, where a dense voxel grid over the queries' box cost more to clear
than the queries did.

:class:`CubeIndex` hashes a scan's points once by cube and answers SciPy's
``cKDTree.query(x, k, distance_upper_bound=r)`` with the same neighbours, visiting the cubes
around each query ring by ring, nearest first: the objects stage asks scan k ~1,200 times
per pair, where building a KD-tree took ~25 ms and its queries more than these searches.
:func:`joined_labels` merges labelled BEV components that come within a gap of each other
(the objects' one motion split across the beams' spacing) by a union-find over BEV cells,
where listing every pair within the gap took ~6x longer.

Units are those of the points (covariances in their square).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from flowslam.compiled_hash import find_slot, grouped_positions, number_keys

__all__ = ["CubeIndex", "box_points", "gathered_covariances", "joined_labels", "knn_within", "near_any_points",
           "neighbourhood_normals", "within_any"]


@njit(cache=True, nogil=True)
def _covariance(points, neighbours, dist, i):
    """(count, xx, yy, zz, xy, xz, yz): the size and the covariance entries of neighbourhood
    ``i`` (the entries undefined when the count is 0)."""
    sx = sy = sz = xx = xy = xz = yy = yz = zz = 0.0
    c = 0
    for j in range(neighbours.shape[1]):
        if dist[i, j] < np.inf:
            p = neighbours[i, j]
            x, y, z = points[p, 0], points[p, 1], points[p, 2]
            sx += x
            sy += y
            sz += z
            xx += x * x
            xy += x * y
            xz += x * z
            yy += y * y
            yz += y * z
            zz += z * z
            c += 1
    if c == 0:
        return 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mx, my, mz = sx / c, sy / c, sz / c
    return c, xx / c - mx * mx, yy / c - my * my, zz / c - mz * mz, xy / c - mx * my, xz / c - mx * mz, yz / c - my * mz


@njit(cache=True, nogil=True)
def _gathered(points, neighbours, dist):
    n = neighbours.shape[0]
    cov = np.empty((n, 3, 3))
    count = np.zeros(n, np.int64)
    for i in range(n):
        c, a, b, cc, d, f, e = _covariance(points, neighbours, dist, i)
        count[i] = c
        if c == 0:
            cov[i] = np.nan
            continue
        cov[i, 0, 0], cov[i, 1, 1], cov[i, 2, 2] = a, b, cc
        cov[i, 0, 1] = cov[i, 1, 0] = d
        cov[i, 0, 2] = cov[i, 2, 0] = f
        cov[i, 1, 2] = cov[i, 2, 1] = e
    return cov, count


@njit(cache=True, nogil=True)
def _smallest_eigenvalue(a, b, c, d, e, f):
    """Smallest eigenvalue of the symmetric matrix [[a, d, f], [d, b, e], [f, e, c]]:
    :func:`~flowslam.sceneflow.refinement.symmetric3.symmetric_eigenvalues`'s formula."""
    m = (a + b + c) / 3
    am, bm, cm = a - m, b - m, c - m
    p2 = (am * am + bm * bm + cm * cm + 2 * (d * d + e * e + f * f)) / 6
    p = np.sqrt(p2)
    det = am * (bm * cm - e * e) - d * (d * cm - e * f) + f * (d * e - bm * f)
    r = det / (2 * p2 * p) if p2 > 0 else 0.0  # p2 == 0: a multiple of I
    phi = np.arccos(min(max(r, -1.0), 1.0)) / 3
    return m + 2 * p * np.cos(phi + 2 * np.pi / 3)


@njit(cache=True, nogil=True)
def _normals(points, neighbours, dist):
    n = neighbours.shape[0]
    normals = np.empty((n, 3))
    count = np.zeros(n, np.int64)
    for i in range(n):
        c, a, b, cc, d, f, e = _covariance(points, neighbours, dist, i)
        count[i] = c
        normals[i] = np.nan
        if c < 3:
            continue
        s = _smallest_eigenvalue(a, b, cc, d, e, f)
        # rows of cov - s I; the longest cross product of two of them (first of equals)
        r0, r1, r2 = (a - s, d, f), (d, b - s, e), (f, e, cc - s)
        best, longest = (0.0, 0.0, 0.0), 0.0
        for u, v in ((r0, r1), (r0, r2), (r1, r2)):
            x = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
            length = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
            if length > longest:
                best, longest = x, length
        if longest > 0:  # else cov - s I is 0: no unique axis (NaN, as the NumPy form gives)
            norm = np.sqrt(longest)
            normals[i, 0], normals[i, 1], normals[i, 2] = best[0] / norm, best[1] / norm, best[2] / norm
    return normals, count


def gathered_covariances(points: np.ndarray, neighbours: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3,3) covariances (E[p p^T] - mean mean^T) of the neighbourhoods that a KD-tree
    query gave: ``neighbours`` (N,k) indices into ``points`` (M,3), ``dist`` (N,k) their
    distances, inf where there was none; and each neighbourhood's size (N,). A
    neighbourhood without points gets NaN."""
    return _gathered(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(neighbours, dtype=np.int64),
                     np.ascontiguousarray(dist, dtype=np.float64))


def neighbourhood_normals(points: np.ndarray, neighbours: np.ndarray,
                          dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) unit normals of the neighbourhoods that a KD-tree query gave (``neighbours``,
    ``dist`` as in :func:`gathered_covariances`): the eigenvector of each covariance's
    smallest eigenvalue (sign arbitrary), NaN where a neighbourhood has fewer than 3 points
    or no unique smallest axis; and each neighbourhood's size (N,). The closed forms of
    :mod:`~flowslam.sceneflow.refinement.symmetric3` (to the last bits of ``arccos`` and
    ``cos``, which NumPy and numba may round differently)."""
    return _normals(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(neighbours, dtype=np.int64),
                    np.ascontiguousarray(dist, dtype=np.float64))


@njit(cache=True, nogil=True)
def _cell_key(p, lo, cell):
    """Packed int64 key (21 bits per axis) of the ``cell``-sized cube holding ``p``, counted from ``lo``."""
    return ((np.int64(np.floor((p[0] - lo[0]) / cell)) << 42) | (np.int64(np.floor((p[1] - lo[1]) / cell)) << 21)
            | np.int64(np.floor((p[2] - lo[2]) / cell)))


@njit(cache=True, nogil=True)
def _cubes(points, rows, lo, cell):
    """``points[rows]`` bucketed by cube of edge ``cell`` counted from ``lo``: (the hash
    table of packed cube keys -- slot keys, slot cube numbers, shift --, the cubes' keys
    (numbered in the order first met), start (cubes + 1,) and members (the rows, by cube,
    in row order): cube c holds ``members[start[c]:start[c + 1]]``, each row's cube)."""
    keys = np.empty(rows.shape[0], np.int64)
    for a in range(rows.shape[0]):
        keys[a] = _cell_key(points[rows[a]], lo, cell)
    slot_keys, slot_cell, shift, cube_of, cube_keys = number_keys(keys)
    start, order = grouped_positions(cube_of, cube_keys.shape[0])
    return slot_keys, slot_cell, shift, cube_keys, start, rows[order], cube_of


@njit(cache=True, nogil=True)
def _near_any(points, x, radius, x_lo, x_hi):
    """:func:`near_any_points` (``x_lo``, ``x_hi``: the queries' minimum and maximum per column)."""
    n = x.shape[0]
    hit = np.zeros(n, np.bool_)
    lo = x_lo - 2 * radius  # a margin of a cell: every query's 27 cells lie inside [lo, hi]
    hi = x_hi + 2 * radius
    # the scan points that can be near a query, bucketed by cube of edge ``radius``
    inside = np.empty(points.shape[0], np.int64)
    m = 0
    for j in range(points.shape[0]):
        if (lo[0] <= points[j, 0] <= hi[0]) and (lo[1] <= points[j, 1] <= hi[1]) and (lo[2] <= points[j, 2] <= hi[2]):
            inside[m] = j
            m += 1
    inside = inside[:m]
    slot_keys, slot_cell, shift, _, start, members, _ = _cubes(points, inside, lo, radius)
    r2 = radius * radius
    for i in range(n):
        ci = np.int64(np.floor((x[i, 0] - lo[0]) / radius))
        cj = np.int64(np.floor((x[i, 1] - lo[1]) / radius))
        ck = np.int64(np.floor((x[i, 2] - lo[2]) / radius))
        for step in range(27):  # its own cube first, then the 26 around it
            s = (step + 13) % 27
            key = ((ci + s // 9 - 1) << 42) | ((cj + (s // 3) % 3 - 1) << 21) | (ck + s % 3 - 1)
            c = slot_cell[find_slot(slot_keys, slot_cell, shift, key)]
            if c == -1:
                continue
            for b in range(start[c], start[c + 1]):
                j = members[b]
                e0, e1, e2 = points[j, 0] - x[i, 0], points[j, 1] - x[i, 1], points[j, 2] - x[i, 2]
                if e0 * e0 + e1 * e1 + e2 * e2 < r2:
                    hit[i] = True
                    break
            if hit[i]:
                break
    return hit


MAX_CELLS_PER_AXIS = (1 << 21) - 8
"""Cubes per axis the packed keys of :func:`near_any_points` can count (21 bits, margins)."""


@njit(cache=True, nogil=True)
def _bounds(x):
    """(all finite, minimum per column (3,), maximum per column (3,)) of (N,3) ``x`` (N >= 1),
    in one pass (the extremes undefined when not all finite)."""
    lo = x[0].copy()
    hi = x[0].copy()
    for i in range(x.shape[0]):
        for d in range(3):
            v = x[i, d]
            if not np.isfinite(v):
                return False, lo, hi
            if v < lo[d]:
                lo[d] = v
            elif v > hi[d]:
                hi[d] = v
    return True, lo, hi


def _cube_bounds(x: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(minimum, maximum) per column of (N,3) ``x`` (N >= 1) when it is finite and spans at
    most ``MAX_CELLS_PER_AXIS`` cubes of edge ``radius`` (> 0) on every axis (with margins);
    else None."""
    if not radius > 0:
        return None
    finite, lo, hi = _bounds(x)
    if not finite or np.any((hi - lo) / radius + 4 > MAX_CELLS_PER_AXIS):
        return None
    return lo, hi


def near_any_points(points: np.ndarray, x: np.ndarray, radius: float) -> np.ndarray | None:
    """(M,) bool: some row of ``points`` (N,3) lies closer than ``radius`` to each query
    ``x`` (M,3), same frame and units; None when the queries span more than
    ``MAX_CELLS_PER_AXIS`` cubes of edge ``radius`` on an axis or are not all finite (the
    caller searches otherwise). Exact: the points near the queries are bucketed by cube of edge ``radius``
    (a hash table), and a query looks at its own cube first, then at the 26 around it,
    which hold every point that close."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if len(x) == 0 or len(points) == 0:
        return np.zeros(len(x), dtype=bool)
    bounds = _cube_bounds(x, radius)
    if bounds is None:
        return None  # (non-finite queries: the caller's KD-tree refuses them, as before)
    return _near_any(np.ascontiguousarray(points, dtype=np.float64), x, float(radius), *bounds)


def within_any(x: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """(M,) bool: one of ``points`` (N,3) closer than ``radius`` to each ``x`` (M,3, same
    frame and units): :func:`near_any_points`, or where that declines the query of a SciPy
    ``cKDTree`` over ``points``: the same answers."""
    near = near_any_points(points, x, radius)
    if near is not None:
        return near
    from scipy.spatial import cKDTree

    tree = cKDTree(points, balanced_tree=False, compact_nodes=False)  # built once, queried once: cheap build
    return np.isfinite(tree.query(x, distance_upper_bound=radius)[0])



@njit(cache=True, nogil=True)
def _kept(sq, j, k, found, best, nb):
    """Offers point ``j`` at squared distance ``sq`` to the sorted ``k`` best of a query
    (squared distances ``best``, indices ``nb``; ``found`` of them filled; equal distances:
    the lower index first); returns the new ``found``."""
    if found == k and (sq > best[k - 1] or (sq == best[k - 1] and j > nb[k - 1])):
        return found
    pos = found if found < k else k - 1
    while pos > 0 and (best[pos - 1] > sq or (best[pos - 1] == sq and nb[pos - 1] > j)):
        best[pos] = best[pos - 1]
        nb[pos] = nb[pos - 1]
        pos -= 1
    best[pos] = sq
    nb[pos] = j
    return found + 1 if found < k else found


@njit(cache=True, nogil=True)
def _knn_within(points, idx, radius, k, lo):
    """:func:`knn_within` (``lo``: the points' minimum per column)."""
    n_points = points.shape[0]
    # the points bucketed by cube of edge ``radius``
    slot_keys, slot_cell, shift, cube_keys, start, members, cell_of = _cubes(points, np.arange(n_points), lo, radius)
    cells = cube_keys.shape[0]
    # the queries grouped by cube: each cube's 27-cube neighbourhood is gathered once
    n = idx.shape[0]
    qstart, queries = grouped_positions(cell_of[idx], cells)
    nb = np.full((n, k), n_points, np.int64)
    dist = np.full((n, k), np.inf)
    best = np.empty(k)
    near = np.empty(n_points, np.int64)
    r2 = radius * radius
    for c in range(cells):
        if qstart[c + 1] == qstart[c]:
            continue
        count = 0
        for s in range(27):
            key = cube_keys[c]
            a, b, c3 = (key >> 42) + s // 9 - 1, ((key >> 21) & 0x1FFFFF) + (s // 3) % 3 - 1, (key & 0x1FFFFF) + s % 3 - 1
            if a < 0 or b < 0 or c3 < 0:
                continue
            other = slot_cell[find_slot(slot_keys, slot_cell, shift, (a << 42) | (b << 21) | c3)]
            if other == -1:
                continue
            for m in range(start[other], start[other + 1]):
                near[count] = members[m]
                count += 1
        for qq in range(qstart[c], qstart[c + 1]):
            i = queries[qq]
            q0, q1, q2 = points[idx[i], 0], points[idx[i], 1], points[idx[i], 2]
            found = 0
            row = nb[i]
            for m in range(count):
                j = near[m]
                d0, d1, d2 = q0 - points[j, 0], q1 - points[j, 1], q2 - points[j, 2]
                sq = d0 * d0 + d1 * d1 + d2 * d2
                if sq < r2:
                    found = _kept(sq, j, k, found, best, row)
            for f in range(found):
                dist[i, f] = np.sqrt(best[f])
    return nb, dist


def knn_within(points: np.ndarray, idx: np.ndarray, radius: float, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The at most ``k`` nearest of ``points`` (N,3) closer than ``radius`` to each of
    ``points[idx]``, nearest first: (neighbour indices (len(idx), k), distances), index N
    and distance inf where there are fewer -- SciPy's ``cKDTree.query(points[idx], k,
    distance_upper_bound=radius)`` of a tree over ``points``, the same numbers (distances
    as the square root of ``dx^2 + dy^2 + dz^2``), from a hash table of cubes of edge
    ``radius``: the queries in one cube share the points of its 27-cube neighbourhood.
    Equal distances come lowest index first (SciPy's order among them is its heap's).
    None where the cubes' packed keys cannot count the points' extent or the points are
    not all finite (the caller asks SciPy). Faster than SciPy where a cube holds a few
    points (the refinement's 0.4 m voxel centroids at r = 1.2 m: 13 vs 21 ms), slower where
    it holds hundreds (raw scans, wide radii)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    k = min(int(k), len(points))
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if len(idx) == 0 or k == 0:
        return np.zeros((len(idx), k), np.int64), np.zeros((len(idx), k))
    bounds = _cube_bounds(points, radius)
    if bounds is None:
        return None
    return _knn_within(points, idx, float(radius), k, bounds[0])


@njit(cache=True, nogil=True, inline="always")
def _gap(q, low, edge):
    """Squared distance from coordinate ``q`` to the interval [``low``, ``low + edge``]."""
    if q < low:
        return (low - q) * (low - q)
    high = low + edge
    return (q - high) * (q - high) if q > high else 0.0


@njit(cache=True, nogil=True, inline="always")
def _ring_margin(q0, q1, q2, f0, f1, f2, lo, edge, ring):
    """How far the query (q0, q1, q2), in the cube (f0, f1, f2) (floats) of a grid of edge
    ``edge`` counted from ``lo``, lies inside the block of cubes within Chebyshev distance
    ``ring`` of its own: every point outside that block is at least this far."""
    return min(q0 - (lo[0] + (f0 - ring) * edge), lo[0] + (f0 + ring + 1) * edge - q0,
               q1 - (lo[1] + (f1 - ring) * edge), lo[1] + (f1 + ring + 1) * edge - q1,
               q2 - (lo[2] + (f2 - ring) * edge), lo[2] + (f2 + ring + 1) * edge - q2)


@njit(cache=True, nogil=True)
def _offer(grouped, members, first, last, q0, q1, q2, r2, k, found, best, nb):
    """Offers the points ``grouped[first:last]`` (the points in cube order: point
    ``members[m]`` is ``grouped[m]``) to the sorted ``k`` best (squared
    distances ``best``, indices ``nb``; ``found`` of them filled) of the query (q0, q1, q2)
    within squared radius ``r2`` (equal distances: the lower index first); returns the new
    ``found``."""
    for m in range(first, last):
        d0, d1, d2 = q0 - grouped[m, 0], q1 - grouped[m, 1], q2 - grouped[m, 2]
        sq = d0 * d0 + d1 * d1 + d2 * d2
        if sq < r2:
            found = _kept(sq, members[m], k, found, best, nb)
    return found


@njit(cache=True, nogil=True)
def _knn_rings(n, grouped, x, radius, k, lo, top, edge, slot_keys, slot_cell, shift, start, members):
    """:meth:`CubeIndex.query`: for each query, the cubes (edge ``edge``) in rings of growing
    Chebyshev distance around its own, each ring's cubes nearest first, until the nearest
    point of the next cube or ring could not be nearer than the k-th found (with a margin
    for rounding) or lies beyond ``radius`` (``top``: the largest cube number per axis; ``n``:
    the number of points; ``grouped``: the points in cube order, ``members[m]`` being
    ``grouped[m]``)."""
    nb = np.full((x.shape[0], k), n, np.int64)
    dist = np.full((x.shape[0], k), np.inf)
    best = np.empty(k)
    r2 = radius * radius
    slack = 1.0 + 1e-9
    reach = np.ceil(radius / edge) + 1
    size = int(2 * reach + 3) ** 3
    bounds = np.empty(size)  # one ring's cubes with their nearest point's squared distance, sorted
    cubes = np.empty(size, np.int64)
    for i in range(x.shape[0]):
        q0, q1, q2 = x[i, 0], x[i, 1], x[i, 2]
        if not (np.isfinite(q0) and np.isfinite(q1) and np.isfinite(q2)):
            continue
        f0, f1, f2 = np.floor((q0 - lo[0]) / edge), np.floor((q1 - lo[1]) / edge), np.floor((q2 - lo[2]) / edge)
        if f0 < -reach or f1 < -reach or f2 < -reach or f0 > top[0] + reach or f1 > top[1] + reach \
                or f2 > top[2] + reach:
            continue  # no cube of the points lies within ``radius``
        ci, cj, ck = np.int64(f0), np.int64(f1), np.int64(f2)
        row = nb[i]
        found = 0
        ring = 0
        while True:
            count = 0
            for a in range(ci - ring, ci + ring + 1):
                if a < 0 or a > top[0]:
                    continue
                ga = _gap(q0, lo[0] + a * edge, edge)
                for b in range(cj - ring, cj + ring + 1):
                    if b < 0 or b > top[1]:
                        continue
                    gab = ga + _gap(q1, lo[1] + b * edge, edge)
                    inner = abs(a - ci) < ring and abs(b - cj) < ring
                    for c in range(ck - ring, ck + ring + 1):
                        if c < 0 or c > top[2] or (inner and abs(c - ck) < ring):
                            continue
                        bound = gab + _gap(q2, lo[2] + c * edge, edge)  # the cube's nearest point, squared
                        if bound > r2 * slack or (found == k and bound > best[k - 1] * slack):
                            continue
                        cube = slot_cell[find_slot(slot_keys, slot_cell, shift, (a << 42) | (b << 21) | c)]
                        if cube == -1:
                            continue
                        pos = count  # insertion by bound
                        while pos > 0 and bounds[pos - 1] > bound:
                            bounds[pos], cubes[pos] = bounds[pos - 1], cubes[pos - 1]
                            pos -= 1
                        bounds[pos], cubes[pos] = bound, cube
                        count += 1
            for t in range(count):
                if found == k and bounds[t] > best[k - 1] * slack:
                    break
                found = _offer(grouped, members, start[cubes[t]], start[cubes[t] + 1], q0, q1, q2, r2, k, found,
                               best, row)
            # every point not visited yet lies at least ``margin`` away
            margin = _ring_margin(q0, q1, q2, f0, f1, f2, lo, edge, ring)
            if margin >= radius or (found == k and best[k - 1] * slack < margin * margin):
                break
            ring += 1
        for f in range(found):
            dist[i, f] = np.sqrt(best[f])
    return nb, dist


@njit(cache=True, nogil=True)
def _root(parent, a):
    """The root of ``a`` in the union-find forest ``parent`` (paths halved on the way)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _joined_labels(xy, labels, n, gap, cell):
    """:func:`joined_labels` (``n``: the number of labels; ``cell``: the BEV cell edge, at
    least ``gap``)."""
    m = xy.shape[0]
    lo0, lo1 = xy[0, 0], xy[0, 1]
    for i in range(m):
        lo0, lo1 = min(lo0, xy[i, 0]), min(lo1, xy[i, 1])
    keys = np.empty(m, np.int64)
    for i in range(m):
        keys[i] = (np.int64(np.floor((xy[i, 0] - lo0) / cell)) << 32) | np.int64(np.floor((xy[i, 1] - lo1) / cell))
    slot_keys, slot_cell, shift, cell_of, cell_keys = number_keys(keys)
    start, order = grouped_positions(cell_of, cell_keys.shape[0])
    parent = np.arange(n)
    g2 = gap * gap
    for c in range(cell_keys.shape[0]):
        ci, cj = cell_keys[c] >> 32, cell_keys[c] & 0xFFFFFFFF
        for step in range(5):  # the cell itself and four of its neighbours: each pair of cells once
            di, dj = (0, 0) if step == 0 else ((0, 1) if step == 1 else ((1, -1) if step == 2 else
                                                                       ((1, 0) if step == 3 else (1, 1))))
            if cj + dj < 0:
                continue
            other = slot_cell[find_slot(slot_keys, slot_cell, shift, ((ci + di) << 32) | (cj + dj))]
            if other == -1:
                continue
            for u in range(start[c], start[c + 1]):
                i = order[u]
                first = u + 1 if other == c else start[other]
                for w in range(first, start[other + 1]):
                    j = order[w]
                    a, b = _root(parent, labels[i]), _root(parent, labels[j])
                    if a == b:
                        continue
                    d0, d1 = xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1]
                    if d0 * d0 + d1 * d1 <= g2:
                        parent[max(a, b)] = min(a, b)
    # number the components in the order of their smallest label (SciPy's connected_components)
    number = np.full(n, -1, np.int64)
    out = np.empty(n, np.int64)
    count = 0
    for a in range(n):
        r = _root(parent, a)
        if number[r] == -1:
            number[r] = count
            count += 1
        out[a] = number[r]
    result = np.empty(m, np.int64)
    for i in range(m):
        result[i] = out[labels[i]]
    return result


def joined_labels(xy: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """(M,) the ``labels`` (0..n-1) of the BEV points ``xy`` (M,2, m) with every two labels
    that have points within ``gap`` (m, distance <= gap) of each other merged, numbered
    from 0 in the order of each merged group's smallest label: what SciPy's
    ``connected_components`` gives on the graph of ``cKDTree(xy).query_pairs(gap)``'s
    pairs across labels, without listing the pairs (a dense object within 0.4 m has tens of
    thousands): points bucketed by BEV cell, and a pair of points is measured only while
    their labels are still apart (union-find)."""
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    if len(xy) == 0:
        return labels.copy()
    if not (gap > 0 and np.isfinite(xy).all() and np.ptp(xy, axis=0).max() / gap < 2.0 ** 30):
        raise ValueError("joined_labels needs finite points spanning fewer than 2^30 gaps and a positive gap")
    return _joined_labels(xy, labels, int(labels.max()) + 1, float(gap), float(gap) * (1.0 + 1e-9))


class CubeIndex:
    """Points (N,3) bucketed once by cube of edge ``edge`` in a hash table, for the searches
    SciPy's ``cKDTree.query(x, k, distance_upper_bound=radius)`` answers, with its numbers
    (distances as the square root of ``dx^2 + dy^2 + dz^2``; equal distances: lowest index
    first): :meth:`query` visits the cubes around each query ring by ring and stops where
    no closer point can remain. Built by :meth:`build` (None where the points are not all
    finite or span more cubes than the packed keys count). It pays where a scan is asked
    many times: the objects stage asks scan k ~1,200 times per KITTI pair for the nearest
    point within 0.3 m and for the 20 within 1 m of its points (their normals)."""

    def __init__(self, points: np.ndarray, edge: float, lo: np.ndarray, hi: np.ndarray):
        self.points, self.edge, self.lo = points, float(edge), lo
        self.top = np.floor((hi - lo) / self.edge)  # the largest cube number per axis
        slot_keys, slot_cell, shift, _, start, members, _ = _cubes(points, np.arange(len(points)), lo, self.edge)
        self._grouped = np.ascontiguousarray(points[members])  # the points cube by cube: searches read them in order
        self._cubes = (slot_keys, slot_cell, shift, start, members)

    @classmethod
    def build(cls, points: np.ndarray, edge: float) -> CubeIndex | None:
        """The index of ``points`` by cubes of edge ``edge`` (> 0, same units)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        bounds = _cube_bounds(points, edge) if len(points) else None
        return None if bounds is None else cls(points, edge, *bounds)

    def query(self, x: np.ndarray, k: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """(distances (M,k), indices (M,k)) of the at most ``k`` points nearest each query
        ``x`` (M,3) closer than ``radius``, nearest first; inf and N where there are fewer
        (all of them for a non-finite query)."""
        if not radius > 0:
            raise ValueError(f"a search radius must be positive, not {radius}")
        k = min(int(k), len(self.points))
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        if len(x) == 0 or k == 0:
            return np.zeros((len(x), k)), np.zeros((len(x), k), np.int64)
        nb, dist = _knn_rings(len(self.points), self._grouped, x, float(radius), k, self.lo, self.top, self.edge,
                              *self._cubes)
        return dist, nb


@njit(cache=True, nogil=True)
def box_points(points, starts, order, n_cols, rows, cols, lo, hi):
    """(K,3) the ``points`` with ``lo <= p <= hi`` (3-vectors) among those in the BEV buckets
    of rows ``rows[0]..rows[1]`` and columns ``cols[0]..cols[1]`` (inclusive, inside the
    grid) of a bucket index (``order``: point indices grouped by row-major bucket id,
    ``starts``: where each bucket id starts in it, ``n_cols``: buckets per row), ordered by
    x, equal x by their index in ``points`` (a stable sort of the index-ordered points)."""
    n = 0
    for r in range(rows[0], rows[1] + 1):
        n += starts[r * n_cols + cols[1] + 1] - starts[r * n_cols + cols[0]]
    inside = np.empty(n, np.int64)
    m = 0
    for r in range(rows[0], rows[1] + 1):
        for b in range(starts[r * n_cols + cols[0]], starts[r * n_cols + cols[1] + 1]):
            j = order[b]
            if (lo[0] <= points[j, 0] <= hi[0]) and (lo[1] <= points[j, 1] <= hi[1]) \
                    and (lo[2] <= points[j, 2] <= hi[2]):
                inside[m] = j
                m += 1
    inside = np.sort(inside[:m])
    x = np.empty(m)
    for a in range(m):
        x[a] = points[inside[a], 0]
    by_x = np.argsort(x, kind="mergesort")  # stable: equal x keep their index order
    out = np.empty((m, 3))
    for a in range(m):
        out[a] = points[inside[by_x[a]]]
    return out
