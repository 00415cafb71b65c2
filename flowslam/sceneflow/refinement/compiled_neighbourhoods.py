"""Covariances of point neighbourhoods from a KD-tree query's result, compiled (numba).

:func:`flowslam.sceneflow.refinement.clusters.neighbourhood_covariances` asks SciPy's
KD-tree for up to k neighbours of each point; gathering them and summing their outer
products with NumPy builds (N, k, 3) temporaries and a batched product of tiny matrices,
which took more time than the query. Here each neighbourhood is summed in one pass.

Units are those of the points (covariances in their square).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["gathered_covariances"]


@njit(cache=True, nogil=True)
def _gathered(points, neighbours, dist):
    n, k = neighbours.shape
    cov = np.empty((n, 3, 3))
    count = np.zeros(n, np.int64)
    for i in range(n):
        sx = sy = sz = xx = xy = xz = yy = yz = zz = 0.0
        c = 0
        for j in range(k):
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
        count[i] = c
        if c == 0:
            cov[i] = np.nan
            continue
        mx, my, mz = sx / c, sy / c, sz / c
        cov[i, 0, 0] = xx / c - mx * mx
        cov[i, 1, 1] = yy / c - my * my
        cov[i, 2, 2] = zz / c - mz * mz
        cov[i, 0, 1] = cov[i, 1, 0] = xy / c - mx * my
        cov[i, 0, 2] = cov[i, 2, 0] = xz / c - mx * mz
        cov[i, 1, 2] = cov[i, 2, 1] = yz / c - my * mz
    return cov, count


def gathered_covariances(points: np.ndarray, neighbours: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3,3) covariances (E[p p^T] - mean mean^T) of the neighbourhoods that a KD-tree
    query gave: ``neighbours`` (N,k) indices into ``points`` (M,3), ``dist`` (N,k) their
    distances, inf where there was none; and each neighbourhood's size (N,). A
    neighbourhood without points gets NaN."""
    return _gathered(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(neighbours, dtype=np.int64),
                     np.ascontiguousarray(dist, dtype=np.float64))
