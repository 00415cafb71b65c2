"""Loop candidates: nearest ring keys among the scans old enough to close a loop with.

A scan becomes *eligible* as a loop partner of the newest scan once it is more than
``exclude_recent_frames`` scans back **and** more than ``exclude_recent_m`` metres
back along the travelled path. Both only grow, so the eligible scans are always a
prefix ``[0, e)`` of the insertion order; the KD-tree (scipy ``cKDTree``) holds the
ring keys of such a prefix and is rebuilt once ``rebuild_every`` more scans became
eligible; the few eligible scans it does not hold yet are compared directly.
"""

from __future__ import annotations

from bisect import bisect_right

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["CandidateIndex"]


class CandidateIndex:
    """Ring keys and path distances of all scans so far (positions = insertion order)."""

    def __init__(self, exclude_recent_frames: int, exclude_recent_m: float, rebuild_every: int):
        self.exclude_recent_frames = int(exclude_recent_frames)
        self.exclude_recent_m = float(exclude_recent_m)
        self.rebuild_every = int(rebuild_every)
        self._keys: list[np.ndarray] = []
        self._path_m: list[float] = []
        self._tree: cKDTree | None = None
        self._tree_size = 0
        self.rebuilds = 0

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, key: np.ndarray, path_m: float) -> None:
        """Append the ring key and the travelled distance (m, non-decreasing) of a new scan."""
        if self._path_m and path_m < self._path_m[-1]:
            raise ValueError("path distance must not decrease")
        self._keys.append(np.asarray(key, dtype=np.float64))
        self._path_m.append(float(path_m))

    def eligible_count(self) -> int:
        """Number ``e`` of leading scans that may close a loop with the newest one."""
        n = len(self._keys)
        by_frames = max(0, n - 1 - self.exclude_recent_frames)
        limit = self._path_m[-1] - self.exclude_recent_m if n else 0.0
        # path is non-decreasing: scans 0..e-1 are those with path <= limit
        by_metres = bisect_right(self._path_m, limit) if n else 0  # O(log n), no list -> array copy
        return min(by_frames, by_metres)

    def query(self, key: np.ndarray, k: int) -> np.ndarray:
        """Positions (ascending key distance) of up to ``k`` eligible scans nearest in ring key.

        The tree answers for the scans it holds; the eligible scans added since its last
        rebuild (fewer than ``rebuild_every``) are compared directly, so nothing lags.
        """
        e = self.eligible_count()
        if e == 0:
            return np.zeros(0, dtype=np.int64)
        if self._tree is None or e - self._tree_size >= self.rebuild_every:
            self._tree = cKDTree(np.stack(self._keys[:e]))
            self._tree_size = e
            self.rebuilds += 1
        key = np.asarray(key, dtype=np.float64)
        dist, idx = self._tree.query(key, k=min(k, self._tree_size))
        dist, idx = np.atleast_1d(dist), np.atleast_1d(idx).astype(np.int64)
        if e > self._tree_size:
            tail = np.arange(self._tree_size, e)
            tail_dist = np.linalg.norm(np.stack(self._keys[self._tree_size : e]) - key, axis=1)
            dist, idx = np.concatenate([dist, tail_dist]), np.concatenate([idx, tail])
        order = np.argsort(dist, kind="stable")[:k]
        return idx[order]
