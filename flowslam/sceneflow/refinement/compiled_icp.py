"""ICP compiled (numba) onto a target whose KD-tree is built once.

Point-to-point (:func:`register`), for the objects stage: it
(:mod:`flowslam.sceneflow.refinement.objects`) registers each object
from up to 7 starts, each coarse to fine (3 stages), onto the same target box of scan k.
Open3D's ``registration_icp`` builds a KD-tree over its target at every call and holds
Python's GIL while it runs; here the box gets one KD-tree (:class:`IcpTarget`) that all
starts and stages share, and the iterations run compiled with the GIL released (the
objects stage then overlaps with the other thread's work).

The iteration is Open3D's point-to-point rule (``TransformationEstimationPointToPoint``,
``ICPConvergenceCriteria``), step for step: the source is moved by the start transform;
each point's correspondence is its nearest target point within ``max_dist``; fitness =
matched share of the source, inlier RMSE = root mean squared distance of the matches;
each iteration solves the rigid motion of the matches in closed form (Umeyama's SVD
without scale; identity when nothing matched), moves the source by it and composes
``T <- update @ T``, and stops after ``max_iterations`` or when fitness and RMSE each
changed by less than the relative thresholds. Tests compare it with Open3D's. Optionally
(``max_turn_rad``) a registration is given up as soon as an iteration turns it farther than
a limit from its start's rotation (not in Open3D: the objects stage's limit on how far an
object may turn in one scan).

Point-to-plane with a Tukey kernel (:func:`register_point_to_plane`), for the static
refinement (:mod:`flowslam.sceneflow.refinement.static`): Open3D's
``TransformationEstimationPointToPlane`` step -- the weighted normal equations of the
residuals ``(x - q) . n``, solved by LDL^T, the update Rz Ry Rx plus a translation --
with the same correspondences and stopping rule; its KD-tree also serves the snapping
(:func:`nearest_within`).

Frames: source points in sensor frame ``k-1`` (m), target points in sensor frame ``k``
(m); a transform maps the source into the target frame (``T_k_{k-1}``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["IcpTarget", "register", "register_point_to_plane", "nearest_within"]

LEAF_SIZE = 32
"""Target points per KD-tree leaf (at most, unless they all coincide)."""


@njit(cache=True, nogil=True)
def _select(points, order, a, b, k, d):
    """Reorders ``order[a:b]`` so that ``order[k]`` holds the point with the k-th smallest
    coordinate ``d``, smaller or equal ones before it, larger or equal ones after it
    (quickselect, median-of-three pivots)."""
    lo, hi = a, b - 1
    while lo < hi:
        m = (lo + hi) // 2
        x, y, z = points[order[lo], d], points[order[m], d], points[order[hi], d]
        pivot = max(min(x, y), min(max(x, y), z))
        i, j = lo, hi
        while i <= j:
            while points[order[i], d] < pivot:
                i += 1
            while points[order[j], d] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True, nogil=True)
def _build(points):
    """KD-tree over (N,3) ``points``: (points in tree order, their original indices, and per
    node its first and past-the-end point, split axis (-1: leaf), children, and bounding box
    corners (nodes, 3))."""
    n = points.shape[0]
    order = np.arange(n)
    capacity = 4 * (n // LEAF_SIZE + 1) + 1  # a split leaves >= LEAF_SIZE / 2 points per leaf: < 4 n / LEAF_SIZE nodes
    start = np.empty(capacity, np.int64)
    end = np.empty(capacity, np.int64)
    axis = np.full(capacity, -1, np.int64)
    left = np.full(capacity, -1, np.int64)
    right = np.full(capacity, -1, np.int64)
    lo = np.zeros((capacity, 3))
    hi = np.zeros((capacity, 3))
    start[0], end[0] = 0, n
    count = 1
    stack = [0]
    while len(stack) > 0:
        node = stack.pop()
        a, b = start[node], end[node]
        if b == a:
            continue
        for d in range(3):
            lo[node, d] = hi[node, d] = points[order[a], d]
        for i in range(a + 1, b):
            for d in range(3):
                v = points[order[i], d]
                if v < lo[node, d]:
                    lo[node, d] = v
                elif v > hi[node, d]:
                    hi[node, d] = v
        d = int(np.argmax(hi[node] - lo[node]))
        if b - a <= LEAF_SIZE or hi[node, d] <= lo[node, d]:  # a leaf (all points equal: however many)
            continue
        mid = (a + b) // 2
        _select(points, order, a, b, mid, d)
        axis[node] = d
        left[node], right[node] = count, count + 1
        start[count], end[count], start[count + 1], end[count + 1] = a, mid, mid, b
        stack.append(count)
        stack.append(count + 1)
        count += 2
    ordered = np.empty((n, 3))
    for i in range(n):
        ordered[i] = points[order[i]]
    return ordered, order, start[:count], end[:count], axis[:count], left[:count], right[:count], lo[:count], hi[:count]


@njit(cache=True, nogil=True)
def _box_sq(q, lo, hi, node):
    """Squared distance from ``q`` to the bounding box of ``node`` (0 inside)."""
    total = 0.0
    for d in range(3):
        if q[d] < lo[node, d]:
            e = lo[node, d] - q[d]
            total += e * e
        elif q[d] > hi[node, d]:
            e = q[d] - hi[node, d]
            total += e * e
    return total


@njit(cache=True, nogil=True)
def _nearest(q, max_sq, hint, ordered, start, end, axis, left, right, lo, hi, stack):
    """Index (into ``ordered``) of the nearest tree point to ``q`` closer than sqrt(max_sq),
    and its squared distance; (-1, max_sq) when none. ``hint`` (an index, or -1): a likely
    answer (the point's previous match), whose distance bounds the search from the start."""
    best, best_sq = -1, max_sq
    if hint >= 0:
        sq = (ordered[hint, 0] - q[0]) ** 2 + (ordered[hint, 1] - q[1]) ** 2 + (ordered[hint, 2] - q[2]) ** 2
        if sq < best_sq:
            best, best_sq = hint, sq
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        if _box_sq(q, lo, hi, node) >= best_sq:  # nothing in it is nearer
            continue
        d = axis[node]
        if d < 0:
            for i in range(start[node], end[node]):
                sq = (ordered[i, 0] - q[0]) ** 2 + (ordered[i, 1] - q[1]) ** 2 + (ordered[i, 2] - q[2]) ** 2
                if sq < best_sq:
                    best, best_sq = i, sq
            continue
        l, r = left[node], right[node]
        if q[d] - hi[l, d] <= lo[r, d] - q[d]:  # nearer the left child: visit it first (pushed last)
            l, r = r, l
        top += 1
        stack[top] = l
        top += 1
        stack[top] = r
    return best, best_sq


@njit(cache=True, nogil=True)
def _match(x, max_dist, ordered, start, end, axis, left, right, lo, hi, stack, src, dst, hints):
    """Nearest target point within ``max_dist`` of each row of ``x`` (Open3D's
    correspondences): fills ``src`` / ``dst`` (matched source row, ordered target row);
    returns (matches, fitness, inlier RMSE). ``hints`` (per row: its previous match or -1)
    start each search and are updated."""
    m, total = 0, 0.0
    max_sq = max_dist * max_dist
    for i in range(x.shape[0]):
        j, sq = _nearest(x[i], max_sq, hints[i], ordered, start, end, axis, left, right, lo, hi, stack)
        hints[i] = j
        if j >= 0:
            src[m], dst[m] = i, j
            total += sq
            m += 1
    if m == 0:
        return 0, 0.0, 0.0
    return m, m / x.shape[0], np.sqrt(total / m)


@njit(cache=True, nogil=True)
def _rigid(x, ordered, src, dst, m):
    """Least-squares rigid motion (4,4) taking ``x[src[:m]]`` onto ``ordered[dst[:m]]``
    (Umeyama without scale); identity when ``m`` is 0."""
    T = np.eye(4)
    if m == 0:
        return T
    ms = np.zeros(3)
    md = np.zeros(3)
    for i in range(m):
        for r in range(3):
            ms[r] += x[src[i], r]
            md[r] += ordered[dst[i], r]
    ms /= m
    md /= m
    sigma = np.zeros((3, 3))
    for i in range(m):
        for r in range(3):
            b = ordered[dst[i], r] - md[r]
            for c in range(3):
                sigma[r, c] += b * (x[src[i], c] - ms[c])
    sigma /= m
    U, _, Vt = np.linalg.svd(sigma)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    T[:3, :3] = R
    T[:3, 3] = md - R @ ms
    return T


@njit(cache=True, nogil=True)
def _moved(T, x):
    """``x`` (N,3) moved by the 4x4 ``T``."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        for r in range(3):
            out[i, r] = T[r, 0] * x[i, 0] + T[r, 1] * x[i, 1] + T[r, 2] * x[i, 2] + T[r, 3]
    return out


@njit(cache=True, nogil=True)
def _register(p, T, stages, max_iterations, relative_fitness, relative_rmse, normals, kernel, min_trace,
              ordered, start, end, axis, left, right, lo, hi):
    """The ICP loop of :func:`register` and :func:`register_point_to_plane`: Open3D's
    correspondences and stopping rule per stage; each update point-to-point (Umeyama)
    when ``normals`` is empty, else point-to-plane with a Tukey kernel of ``kernel`` (m;
    <= 0: the stage's distance) on the tree-ordered ``normals``. Returns (T, turned):
    ``turned`` when an iteration left the rotation of T farther from the start's than
    ``min_trace`` allows (the trace of the relative rotation, 1 + 2 cos(angle), fell below
    it), where the loop stops."""
    n = p.shape[0]
    R0 = T[:3, :3].copy()
    src = np.empty(n, np.int64)
    dst = np.empty(n, np.int64)
    stack = np.empty(2 * len(start) + 2, np.int64)
    hints = np.full(n, -1, np.int64)
    plane = normals.shape[0] > 0
    for max_dist in stages:
        x = _moved(T, p)
        m, fitness, rmse = _match(x, max_dist, ordered, start, end, axis, left, right, lo, hi, stack, src, dst, hints)
        for _ in range(max_iterations):
            if plane:
                update = _plane_update(x, ordered, normals, src, dst, m, max_dist if kernel <= 0 else kernel)
            else:
                update = _rigid(x, ordered, src, dst, m)
            T = update @ T
            if min_trace > -1.0 and _turn_trace(T, R0) < min_trace:
                return T, True
            x = _moved(update, x)
            previous_fitness, previous_rmse = fitness, rmse
            m, fitness, rmse = _match(x, max_dist, ordered, start, end, axis, left, right, lo, hi, stack, src, dst, hints)
            if abs(previous_fitness - fitness) < relative_fitness and abs(previous_rmse - rmse) < relative_rmse:
                break
    return T, False


@njit(cache=True, nogil=True)
def _turn_trace(T, R0):
    """Trace of the rotation from ``R0`` (3,3) to T's (1 + 2 cos of the angle between them)."""
    total = 0.0
    for r in range(3):
        for c in range(3):
            total += T[r, c] * R0[r, c]
    return total


class IcpTarget:
    """A target cloud (N,3, m) with its KD-tree, built once and shared by every
    :func:`register` onto it."""

    def __init__(self, points: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self._tree = _build(self.points)


def register(p: np.ndarray, target: IcpTarget, T: np.ndarray, stages, max_iterations: int,
             relative_fitness: float = 1e-6, relative_rmse: float = 1e-6,
             max_turn_rad: float | None = None) -> np.ndarray | None:
    """Point-to-point ICP of ``p`` (N,3) onto ``target`` from ``T`` (4,4), once per
    correspondence distance in ``stages`` (m, coarse to fine), each stage at most
    ``max_iterations`` iterations of Open3D's rule (module doc); returns the final 4x4 T.
    With ``max_turn_rad``: None as soon as an iteration turns T's rotation farther than
    that (rad) from the start's (the registration is given up)."""
    ordered, _, start, end, axis, left, right, lo, hi = target._tree
    T, turned = _register(np.ascontiguousarray(p, dtype=np.float64), np.ascontiguousarray(T, dtype=np.float64),
                          np.asarray(stages, dtype=np.float64), int(max_iterations), float(relative_fitness),
                          float(relative_rmse), _NO_NORMALS, 0.0, _min_trace(max_turn_rad), ordered, start, end, axis,
                          left, right, lo, hi)
    return None if turned else T


def _min_trace(max_turn_rad: float | None) -> float:
    """The smallest trace of a relative rotation within ``max_turn_rad`` (rad) of none;
    -1 (every rotation's trace is at least that) for no limit."""
    if max_turn_rad is None or not max_turn_rad < np.pi:
        return -1.0
    return 1.0 + 2.0 * float(np.cos(max_turn_rad))


_NO_NORMALS = np.zeros((0, 3))
"""The normals argument of :func:`_register` for point-to-point updates."""


# ------------------------------------------------------------------ point-to-plane
@njit(cache=True, nogil=True)
def _ldlt_solve(A, b):
    """``x`` with ``A x = b`` for a symmetric positive semi-definite ``A`` (n, n): LDL^T with
    symmetric pivoting (largest remaining diagonal first), and a zero pivot's unknown set
    to 0 (the pseudo-inverse of D), as Eigen's ``ldlt().solve`` that Open3D uses."""
    n = A.shape[0]
    M = A.copy()
    perm = np.arange(n)
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(M[i, i]) > abs(M[p, p]):
                p = i
        if p != k:  # swap rows and columns k and p
            for j in range(n):
                M[k, j], M[p, j] = M[p, j], M[k, j]
            for j in range(n):
                M[j, k], M[j, p] = M[j, p], M[j, k]
            perm[k], perm[p] = perm[p], perm[k]
        d = M[k, k]
        if d == 0.0:
            continue
        for i in range(k + 1, n):
            M[i, k] /= d
        for i in range(k + 1, n):
            for j in range(k + 1, i + 1):
                M[i, j] -= M[i, k] * M[j, k] * d
                M[j, i] = M[i, j]
    y = np.empty(n)
    for i in range(n):
        y[i] = b[perm[i]]
    for i in range(n):  # L y = P b (unit lower triangle)
        for j in range(i):
            y[i] -= M[i, j] * y[j]
    tiny = np.finfo(np.float64).tiny
    for i in range(n):
        y[i] = y[i] / M[i, i] if abs(M[i, i]) > tiny else 0.0
    for i in range(n - 1, -1, -1):  # L^T z = y
        for j in range(i + 1, n):
            y[i] -= M[j, i] * y[j]
    x = np.empty(n)
    for i in range(n):
        x[perm[i]] = y[i]
    return x


@njit(cache=True, nogil=True)
def _pose_from_twist(v):
    """4x4 of the 6-vector (rx, ry, rz, tx, ty, tz): R = Rz(rz) Ry(ry) Rx(rx), t as given
    (Open3D's ``TransformVector6dToMatrix4d``)."""
    cx, sx = np.cos(v[0]), np.sin(v[0])
    cy, sy = np.cos(v[1]), np.sin(v[1])
    cz, sz = np.cos(v[2]), np.sin(v[2])
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    T = np.eye(4)
    T[:3, :3] = (Rz @ Ry) @ Rx
    T[0, 3], T[1, 3], T[2, 3] = v[3], v[4], v[5]
    return T


@njit(cache=True, nogil=True)
def _plane_update(x, ordered, normals, src, dst, m, kernel):
    """One Gauss-Newton step of the Tukey-weighted point-to-plane residuals
    ``(x_i - q_j) . n_j`` of the matches (Open3D's ``TransformationEstimationPointToPlane``
    with ``TukeyLoss(kernel)``): J = [x_i x n_j, n_j], weight (1 - (r / kernel)^2)^2 within
    ``kernel``, else 0; the update as a 4x4 (identity without matches)."""
    if m == 0:
        return np.eye(4)
    JTJ = np.zeros((6, 6))
    JTr = np.zeros(6)
    J = np.empty(6)
    for i in range(m):
        a, q = src[i], dst[i]
        x0, x1, x2 = x[a, 0], x[a, 1], x[a, 2]
        n0, n1, n2 = normals[q, 0], normals[q, 1], normals[q, 2]
        r = (x0 - ordered[q, 0]) * n0 + (x1 - ordered[q, 1]) * n1 + (x2 - ordered[q, 2]) * n2
        e = abs(r)
        if e > kernel:
            continue
        u = 1.0 - (e / kernel) ** 2
        w = u * u
        J[0], J[1], J[2] = x1 * n2 - x2 * n1, x2 * n0 - x0 * n2, x0 * n1 - x1 * n0
        J[3], J[4], J[5] = n0, n1, n2
        for row in range(6):
            wj = w * J[row]
            JTr[row] += wj * r
            for col in range(row + 1):
                JTJ[row, col] += wj * J[col]
    for row in range(6):
        for col in range(row + 1, 6):
            JTJ[row, col] = JTJ[col, row]
    return _pose_from_twist(_ldlt_solve(JTJ, -JTr))


def register_point_to_plane(p: np.ndarray, target: IcpTarget, normals: np.ndarray, T: np.ndarray, stages,
                            max_iterations: int, relative_fitness: float = 1e-6,
                            relative_rmse: float = 1e-6, kernel: float | None = None) -> np.ndarray:
    """Point-to-plane ICP of ``p`` (N,3) onto ``target`` and its unit ``normals`` (one per
    target point, in its order) from ``T`` (4,4): per correspondence distance in ``stages``
    (m, coarse to fine) at most ``max_iterations`` iterations of Open3D's rule with a Tukey
    kernel of ``kernel`` (m; None: that stage's distance) (``registration_icp`` with
    ``TransformationEstimationPointToPlane(TukeyLoss(k))``); returns the final T.
    The same steps as Open3D: nearest target point within the distance, the weighted
    normal equations solved by LDL^T with pivoting, the update as Rz Ry Rx and a
    translation, the same stopping rule; sums in the source's order (Open3D sums per
    thread), so the numbers agree to rounding."""
    ordered, order, start, end, axis, left, right, lo, hi = target._tree
    tree_normals = np.ascontiguousarray(np.asarray(normals, dtype=np.float64)[order])
    return _register(np.ascontiguousarray(p, dtype=np.float64), np.ascontiguousarray(T, dtype=np.float64),
                     np.asarray(stages, dtype=np.float64), int(max_iterations), float(relative_fitness),
                     float(relative_rmse), tree_normals, -1.0 if kernel is None else float(kernel), -1.0,
                     ordered, start, end, axis, left, right, lo, hi)[0]


@njit(cache=True, nogil=True)
def _nearest_all(x, max_dist, order, ordered, start, end, axis, left, right, lo, hi):
    stack = np.empty(2 * len(start) + 2, np.int64)
    found = np.full(x.shape[0], -1, np.int64)
    max_sq = max_dist * max_dist
    for i in range(x.shape[0]):
        j, _ = _nearest(x[i], max_sq, -1, ordered, start, end, axis, left, right, lo, hi, stack)
        if j >= 0:
            found[i] = order[j]
    return found


def nearest_within(target: IcpTarget, x: np.ndarray, max_dist: float) -> np.ndarray:
    """(M,) index (into ``target.points``) of the nearest target point closer than
    ``max_dist`` to each row of ``x`` (M,3), -1 where there is none (SciPy's
    ``query(x, distance_upper_bound=max_dist)``; among equally near points either may come)."""
    ordered, order, start, end, axis, left, right, lo, hi = target._tree
    return _nearest_all(np.ascontiguousarray(x, dtype=np.float64), float(max_dist), order, ordered, start, end, axis,
                        left, right, lo, hi)
