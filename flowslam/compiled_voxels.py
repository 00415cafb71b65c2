"""Points grouped by voxel, compiled (numba): what :func:`flowslam.mapping.voxel_ids`,
:func:`~flowslam.mapping.group_keys` and :func:`~flowslam.mapping.voxel_means` compute, the
same numbers, without NumPy's sort of every point.

NumPy groups N keys with a stable argsort of all of them (~3 ms for a 120k-point scan)
plus a handful of gathers and scatters; here each key goes through a hash table once
(:mod:`flowslam.compiled_hash`; first come, first numbered), only the V distinct keys are
sorted (V is a fraction of N at map resolutions), and the sums run in one pass in point
order, as ``np.bincount`` sums.
:func:`open3d_voxel_means` gives Open3D's ``voxel_down_sample`` (its grid, its centroids
and mean normals to the bit) in voxel-key order, for the loop closer and scan-to-map.
Imported on first use, so that a command that never groups points never loads numba.

Units: those of the points (m); keys are int64.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from flowslam.compiled_hash import number_keys

__all__ = ["group_means", "grouped_keys", "open3d_voxel_means", "packed_voxel_keys"]


@njit(cache=True, nogil=True)
def _grouped(keys):
    _, _, _, group, distinct = number_keys(keys)  # numbered in the order first met
    order = np.argsort(distinct)  # distinct keys: the sort needs no stability
    rank = np.empty(distinct.shape[0], np.int64)
    for r in range(order.shape[0]):
        rank[order[r]] = r
    inverse = np.empty(keys.shape[0], np.int64)
    counts = np.zeros(distinct.shape[0], np.int64)
    for i in range(keys.shape[0]):
        inverse[i] = rank[group[i]]
        counts[inverse[i]] += 1
    return inverse, counts


def grouped_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(inverse (N,), counts (V,))`` of (N,) int64 ``keys``, groups numbered in key order:
    :func:`flowslam.mapping.group_keys`'s result."""
    return _grouped(np.ascontiguousarray(keys, dtype=np.int64))


@njit(cache=True, nogil=True)
def _packed(points, voxel_size):
    n = points.shape[0]
    q = np.empty((n, 3), np.int64)
    low = np.empty(3, np.int64)
    for d in range(3):
        low[d] = np.iinfo(np.int64).max
    for i in range(n):
        for d in range(3):
            q[i, d] = np.int64(np.floor(points[i, d] / voxel_size))
            low[d] = min(low[d], q[i, d])
    keys = np.empty(n, np.int64)
    top = 0
    for i in range(n):
        a, b, c = q[i, 0] - low[0], q[i, 1] - low[1], q[i, 2] - low[2]
        top = max(top, a, b, c)
        keys[i] = (a << 42) | (b << 21) | c
    return keys, top < (1 << 21)


def packed_voxel_keys(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, bool]:
    """((N,) int64 key of each point's ``voxel_size`` voxel: integer coordinates relative
    to the smallest, 21 bits per axis; whether every coordinate fits in 21 bits (else the
    keys are meaningless)) of (N,3) points (N >= 1), as :func:`flowslam.mapping.voxel_ids`
    packs them."""
    return _packed(np.ascontiguousarray(points, dtype=np.float64), float(voxel_size))


@njit(cache=True, nogil=True)
def _means(inverse, counts, values, rows):
    """(V, K) mean per group of the rows ``values[rows[a]]`` (group ``inverse[a]``), summed in
    the order of ``rows``."""
    out = np.zeros((counts.shape[0], values.shape[1]))
    for a in range(rows.shape[0]):
        for j in range(values.shape[1]):
            out[inverse[a], j] += values[rows[a], j]
    for v in range(counts.shape[0]):
        for j in range(values.shape[1]):
            out[v, j] /= counts[v]
    return out


def group_means(inverse: np.ndarray, counts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(V, K) mean of the (N, K) ``values`` per group (``inverse``, ``counts`` of
    :func:`grouped_keys`), summed in point order: ``np.bincount(inverse, values[:, j]) /
    counts``, column by column, to the bit."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    return _means(np.ascontiguousarray(inverse, dtype=np.int64), np.ascontiguousarray(counts, dtype=np.int64),
                  values, np.arange(len(values)))


@njit(cache=True, nogil=True)
def _open3d_keys(points, keep, voxel_size):
    """Open3D's voxel of each kept point, packed (21 bits per axis): indices
    ``floor((p - (min - voxel / 2)) / voxel)`` with the minimum over the kept points, as
    ``PointCloud::VoxelDownSample`` computes them; (kept indices, keys, whether all fit)."""
    n = points.shape[0]
    kept = np.empty(n, np.int64)
    m = 0
    lo = np.full(3, np.inf)
    for i in range(n):
        if keep[i]:
            kept[m] = i
            m += 1
            for d in range(3):
                lo[d] = min(lo[d], points[i, d])
    origin = np.empty(3)
    for d in range(3):
        origin[d] = lo[d] - voxel_size * 0.5
    keys = np.empty(m, np.int64)
    fits = True
    for a in range(m):
        i = kept[a]
        key = np.int64(0)
        for d in range(3):
            v = np.int64(np.floor((points[i, d] - origin[d]) / voxel_size))
            if v >= (1 << 21):
                fits = False
            key = (key << 21) | v
        keys[a] = key
    return kept[:m], keys, fits


def open3d_voxel_means(points: np.ndarray, voxel_size: float, keep: np.ndarray | None = None,
                       normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """``(centroids (V,3), mean normals (V,3) or None)``: Open3D's ``voxel_down_sample`` of the
    (N,3) ``points`` (m; those with ``keep`` (N,) bool only), the same voxels (a grid from
    the kept points' minimum minus half a voxel) and the same numbers (sums in point order,
    divided by the count), in key order (x, then y, then z) instead of the order of Open3D's
    hash map. ``normals`` (N,3) are averaged alike (not normalised). Empty input: (0,3)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    keep = np.ones(len(points), dtype=bool) if keep is None else np.ascontiguousarray(keep, dtype=bool)
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0 (m), got {voxel_size}")
    columns = points if normals is None else np.hstack([points, np.asarray(normals, dtype=np.float64)])
    if not keep.any():
        return np.zeros((0, 3)), None if normals is None else np.zeros((0, 3))
    kept, keys, fits = _open3d_keys(points, keep, float(voxel_size))
    if not fits:
        raise ValueError(f"voxel size {voxel_size} m is too small for the points' extent")
    inverse, counts = grouped_keys(keys)
    means = _means(inverse, counts, np.ascontiguousarray(columns), kept)
    return np.ascontiguousarray(means[:, :3]), None if normals is None else np.ascontiguousarray(means[:, 3:])
