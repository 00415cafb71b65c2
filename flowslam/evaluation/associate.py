"""Pair the poses of an estimate with those of the ground truth.

With timestamps on both sides the poses are matched by time (nearest
neighbour within ``max_diff`` seconds), the way evo's ``evo_ape`` / ``evo_rpe``
do it: the trajectory with fewer poses is walked, each of its stamps takes the
closest stamp of the other one (ties go to the earlier stamp), and ``offset``
(seconds) is added to the *estimate's* stamps for the comparison only. Unlike
evo, a pose of the longer trajectory is never used twice: where two stamps pick
the same partner, the closer one keeps it (this only differs from evo when
``max_diff`` exceeds half the sampling period). Without timestamps on either
side the poses are matched by index and the counts must agree.
"""

from __future__ import annotations

import numpy as np

from flowslam.errors import InputError
from flowslam.trajectory import Trajectory

__all__ = ["match_timestamps", "associate"]


def _nearest_sorted(short: np.ndarray, long: np.ndarray, max_diff: float):
    """Nearest neighbours of ``short`` stamps among sorted ``long`` stamps (ties: earlier)."""
    k = np.searchsorted(long, short, side="right")
    k = np.minimum(k, len(long) - 1)
    diff_ub = long[k] - short
    diff_lb = np.where(k > 0, short - long[np.maximum(k - 1, 0)], np.inf)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    in_range = (short >= long[0] - max_diff) & (short <= long[-1] + max_diff)
    ok = in_range & (take_ub | take_lb)
    idx_long = np.where(take_ub, k, k - 1)
    return np.flatnonzero(ok), idx_long[ok]


def _nearest_unsorted(short: np.ndarray, long: np.ndarray, max_diff: float, chunk: int = 1024):
    """Brute-force nearest neighbours (first index on ties) for unsorted ``long`` stamps."""
    best = np.empty(len(short), dtype=np.int64)
    for s in range(0, len(short), chunk):
        best[s : s + chunk] = np.argmin(np.abs(long[None, :] - short[s : s + chunk, None]), axis=1)
    ok = np.abs(long[best] - short) <= max_diff
    return np.flatnonzero(ok), best[ok]


def match_timestamps(
    stamps_short: np.ndarray, stamps_long: np.ndarray, max_diff: float = 0.01, offset_long: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_short, i_long)`` of unique nearest-neighbour time matches.

    Every stamp of ``stamps_short`` (s) is matched to the closest stamp of
    ``stamps_long + offset_long`` (s) if they are at most ``max_diff`` (s) apart;
    ties go to the earlier stamp. Where several short stamps pick the same long
    stamp only the closest one (the first on a tie) keeps it. Both index arrays
    are in increasing order of ``i_short``.
    """
    short = np.asarray(stamps_short, dtype=np.float64).reshape(-1)
    long = np.asarray(stamps_long, dtype=np.float64).reshape(-1) + offset_long
    if len(short) == 0 or len(long) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if np.all(np.diff(long) >= 0):
        i_short, i_long = _nearest_sorted(short, long, max_diff)
    else:
        i_short, i_long = _nearest_unsorted(short, long, max_diff)
    i_short, i_long = i_short.astype(np.int64), i_long.astype(np.int64)
    if len(np.unique(i_long)) != len(i_long):
        dt = np.abs(long[i_long] - short[i_short])
        order = np.lexsort((np.arange(len(i_long)), dt))  # closest first, then earliest
        _, first = np.unique(i_long[order], return_index=True)
        keep = np.sort(order[first])
        i_short, i_long = i_short[keep], i_long[keep]
    return i_short, i_long


def associate(
    est: Trajectory,
    gt: Trajectory,
    max_diff: float = 0.01,
    offset: float = 0.0,
    *,
    est_name: str = "estimate",
    gt_name: str = "ground truth",
) -> tuple[Trajectory, Trajectory]:
    """Matched copies ``(est_matched, gt_matched)`` of equal length, pose ``k`` with pose ``k``.

    - Both have timestamps: nearest-neighbour time association (see the module
      docstring) with ``max_diff`` (s) and ``offset`` (s) added to ``est``'s stamps;
      the returned trajectories keep their own, unshifted stamps.
    - Either lacks timestamps: index association; the pose counts must be equal.

    Raises ``InputError`` (naming ``est_name`` / ``gt_name``) when the counts differ
    in index mode or when no pose pair associates.
    """
    if max_diff < 0:
        raise InputError(None, f"max_diff must be >= 0 s, got {max_diff}")
    if len(est) == 0 or len(gt) == 0:
        empty = est_name if len(est) == 0 else gt_name
        raise InputError(None, f"{empty} holds no poses; nothing to associate")
    if est.timestamps is None or gt.timestamps is None:
        if len(est) != len(gt):
            missing = [n for n, t in ((est_name, est), (gt_name, gt)) if t.timestamps is None]
            raise InputError(
                None,
                f"{est_name} has {len(est)} poses but {gt_name} has {len(gt)}; without timestamps "
                f"(missing in {' and '.join(missing)}) poses are matched by index, so the counts "
                "must be equal",
            )
        return est, gt

    # Like evo: walk the trajectory with fewer poses (the estimate on a tie), and
    # shift the estimate's stamps by +offset (= the GT's by -offset).
    est_longer = len(est) > len(gt)
    if est_longer:
        i_gt, i_est = match_timestamps(gt.timestamps, est.timestamps, max_diff, offset)
    else:
        i_est, i_gt = match_timestamps(est.timestamps, gt.timestamps, max_diff, -offset)
    if len(i_est) == 0:
        raise InputError(
            None,
            f"no timestamps of {est_name} ({est.timestamps.min():.6f}..{est.timestamps.max():.6f} s, "
            f"{len(est)} poses) match {gt_name} ({gt.timestamps.min():.6f}..{gt.timestamps.max():.6f} s, "
            f"{len(gt)} poses) within max_diff {max_diff} s (offset {offset} s added to {est_name})",
        )
    return est.subset(i_est), gt.subset(i_gt)
