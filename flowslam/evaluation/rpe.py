"""Relative pose error (RPE), with the numbers of evo's ``evo_rpe``.

For a pose pair ``(i, j)`` of the estimate ``P`` and the GT ``Q`` (both
``T_world_sensor``), the relative motions are ``Q_i_j = inv(Q_i) @ Q_j`` and
``P_i_j = inv(P_i) @ P_j`` (pose j in frame i) and the error is

    E_ij = inv(Q_i_j) @ P_i_j        (TUM RGB-D benchmark / evo's ``rpe_base``)

i.e. the estimated motion seen from the true one; identity means no error.
``translation`` reports ``|t(E_ij)|`` (m), ``rotation_angle_deg`` its rotation
angle (deg), etc. (see ``_common.POSE_RELATIONS``).

Pairs (evo's ``id_pairs_from_delta``):

- ``delta_unit="frames"``: ``(0, d), (d, 2d), ...``; with ``all_pairs``
  every ``(i, i + d)``.
- ``delta_unit="m"``: travelled distance along a path (the GT path by default,
  ``pairs_from="gt"``; evo's default is the estimate's path, i.e. ``evo_rpe``
  without ``--pairs_from_reference``). Consecutive mode: start at pose 0, sum the
  step lengths and close a pair at the first pose where the sum reaches
  ``delta``, then restart from there. ``all_pairs``: for every ``i`` the ``j > i``
  whose distance along the path is closest to ``delta``, kept if within
  ``rel_delta_tol * delta``.
"""

from __future__ import annotations

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError

from ._common import as_poses, check_same_length, pose_error_values, relation_unit
from .align import align_trajectory
from .stats import summary

__all__ = [
    "DELTA_UNITS",
    "accumulated_distances",
    "pairs_by_index",
    "pairs_by_path",
    "rpe_pairs",
    "relative_errors",
    "rpe_errors",
    "rpe",
]

DELTA_UNITS = ("frames", "m")


def accumulated_distances(positions: np.ndarray) -> np.ndarray:
    """(N,) distance (m) travelled from the first position, along the (N,3) polyline."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    steps = np.linalg.norm(positions[:-1] - positions[1:], axis=1)
    return np.concatenate(([0.0], np.cumsum(steps)))


def pairs_by_index(n: int, delta: int, all_pairs: bool = False) -> np.ndarray:
    """(K,2) index pairs ``(i, i + delta)`` among ``n`` poses (consecutive: i = 0, delta, 2 delta, ...)."""
    if all_pairs:
        i = np.arange(max(n - delta, 0))
        return np.stack([i, i + delta], axis=1).astype(np.int64)
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1).astype(np.int64)


def pairs_by_path(
    positions: np.ndarray, delta: float, tol: float = 0.0, all_pairs: bool = False
) -> np.ndarray:
    """(K,2) index pairs about ``delta`` metres apart along the (N,3) path.

    Consecutive mode (``tol`` unused): the running sum of step lengths, reset at
    every accepted pose, must reach ``delta``. ``all_pairs``: for each ``i`` the
    first ``j > i`` minimising ``|(d_j - d_i) - delta|`` over the accumulated
    distances ``d``, kept if that is ``<= tol`` (m).
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(positions)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    if not all_pairs:
        # Sequential by nature (the sum restarts at each accepted pose); O(N).
        steps = np.linalg.norm(positions[1:] - positions[:-1], axis=1).tolist()
        ids = [0]
        run = 0.0
        for k, step in enumerate(steps, start=1):
            run += step
            if run >= delta:
                ids.append(k)
                run = 0.0
        ids = np.asarray(ids, dtype=np.int64)
        return np.stack([ids[:-1], ids[1:]], axis=1)

    d = accumulated_distances(positions)
    # Only j with |d_j - d_i - delta| <= tol can be accepted, and then the
    # minimiser lies among them: search a slightly padded window per i.
    pad = 1e-9 * max(1.0, float(d[-1]))
    lo = np.searchsorted(d, d[:-1] + delta - tol - pad, side="left")
    hi = np.searchsorted(d, d[:-1] + delta + tol + pad, side="right")
    pairs = []
    for i in range(n - 1):
        a, b = max(lo[i], i + 1), hi[i]
        if a >= b:
            continue
        err = np.abs((d[a:b] - d[i]) - delta)
        k = int(np.argmin(err))
        if err[k] <= tol:
            pairs.append((i, a + k))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def rpe_pairs(
    poses: np.ndarray,
    delta: float,
    delta_unit: str = "frames",
    all_pairs: bool = False,
    rel_delta_tol: float = 0.1,
) -> np.ndarray:
    """(K,2) pose-index pairs of one trajectory for an RPE step of ``delta`` ``delta_unit``."""
    poses = as_poses(poses)
    if delta_unit not in DELTA_UNITS:
        raise InputError(None, f"unknown RPE delta unit {delta_unit!r}; use 'frames' or 'm'")
    if not np.isfinite(delta) or delta <= 0:
        raise InputError(None, f"RPE delta must be a positive number, got {delta}")
    if delta_unit == "frames":
        if float(delta) != int(delta):
            raise InputError(None, f"RPE delta in frames must be an integer, got {delta}")
        return pairs_by_index(len(poses), int(delta), all_pairs)
    return pairs_by_path(poses[:, :3, 3], float(delta), float(delta) * rel_delta_tol, all_pairs)


def relative_errors(est, gt, pairs: np.ndarray) -> np.ndarray:
    """Error transforms ``E_ij = inv(inv(Q_i) Q_j) @ inv(P_i) P_j`` (K,4,4) for index pairs (K,2)."""
    P, Q = as_poses(est), as_poses(gt)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    Q_rel = geometry.inv(Q[i]) @ Q[j]
    P_rel = geometry.inv(P[i]) @ P[j]
    return geometry.inv(Q_rel) @ P_rel


def rpe_errors(est, gt, pairs: np.ndarray, pose_relation: str = "translation") -> np.ndarray:
    """Per-pair RPE (K,) for index pairs (K,2), in ``relation_unit(pose_relation)``."""
    return pose_error_values(relative_errors(est, gt, pairs), pose_relation)


def rpe(
    est,
    gt,
    *,
    delta: float = 1,
    delta_unit: str = "frames",
    all_pairs: bool = False,
    pose_relation: str = "translation",
    pairs_from: str = "gt",
    rel_delta_tol: float = 0.1,
    align: bool = False,
    correct_scale: bool = False,
) -> dict:
    """RPE statistics of associated trajectories (``Trajectory`` or (N,4,4) arrays).

    ``delta`` in ``delta_unit`` (``"frames"`` or ``"m"``), pairs as in the module
    docstring, taken along ``pairs_from`` (``"gt"`` or ``"est"``; only matters
    for metres). ``align`` / ``correct_scale`` as in :func:`~.ape.ape` (an SE(3)
    alignment leaves the RPE unchanged; a scale correction does not).

    Returns ``{pose_relation, unit, delta, delta_unit, all_pairs, pairs_from,
    n_pairs, rmse, mean, median, std, min, max, sse, n}``. Raises ``InputError``
    if the trajectories give no pair for this delta.
    """
    unit = relation_unit(pose_relation)
    if pairs_from not in ("gt", "est"):
        raise InputError(None, f"pairs_from must be 'gt' or 'est', got {pairs_from!r}")
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "RPE")
    if align or correct_scale:
        P, _, _ = align_trajectory(P, Q, correct_scale, only_scale=correct_scale and not align)
    pairs = rpe_pairs(Q if pairs_from == "gt" else P, delta, delta_unit, all_pairs, rel_delta_tol)
    if len(pairs) == 0:
        path = accumulated_distances((Q if pairs_from == "gt" else P)[:, :3, 3])[-1]
        raise InputError(
            None,
            f"RPE delta = {delta} {delta_unit} gives no pose pair among {len(P)} poses "
            f"({pairs_from} path {path:.3f} m); use a smaller delta",
        )
    return {
        "pose_relation": pose_relation,
        "unit": unit,
        "delta": delta,
        "delta_unit": delta_unit,
        "all_pairs": bool(all_pairs),
        "pairs_from": pairs_from,
        "n_pairs": int(len(pairs)),
        **summary(rpe_errors(P, Q, pairs, pose_relation)),
    }
