"""Bird's-eye-view grouping of points: connected components and a local ground test.

Points (N,3) in any sensor frame with z up; cells in metres.
"""

from __future__ import annotations

import numpy as np

from flowslam.mapping import voxel_ids

__all__ = ["above_ground", "bev_clusters"]


def bev_clusters(points: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int label of 8-connected components of the occupied ``cell`` x ``cell`` BEV cells."""
    from scipy import ndimage

    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
    return labels[ij[:, 0], ij[:, 1]] - 1


def above_ground(points: np.ndarray, cell: float, clearance: float) -> np.ndarray:
    """(N,) bool: points higher than the lowest point of their ``cell`` x ``cell`` BEV cell
    plus ``clearance`` (m): a local ground estimate good enough to tell the road from what
    stands on it."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    inverse, counts = voxel_ids(points * [1.0, 1.0, 0.0], cell)  # BEV cells: z flattened
    lowest = np.full(len(counts), np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    return points[:, 2] > lowest[inverse] + clearance
