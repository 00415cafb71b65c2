"""Aligning an estimated trajectory to the ground truth before comparing absolute poses.

Umeyama (1991, "Least-squares estimation of transformation parameters between
two point patterns") gives the rotation ``R``, translation ``t`` (m) and scale
``s`` minimising ``sum_i |dst_i - (s R src_i + t)|^2``. Applied to a trajectory
(the estimate, ``src``) it maps the estimate's world frame into the GT's world
frame: ``T_gtworld_estworld = [R | t]`` with the estimate's translations scaled
by ``s`` first, i.e. each pose becomes ``[R R_i | s R t_i + t]`` (evo's
``align`` convention: scale the positions, then left-multiply by ``[R | t]``).
"""

from __future__ import annotations

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError
from flowslam.trajectory import Trajectory

from ._common import as_poses, check_same_length

__all__ = ["RANK_RTOL", "WELL_CONDITIONED_RTOL", "umeyama", "apply_alignment", "align_trajectory", "align_origin"]

#: Default: singular values of the cross-covariance below this fraction of the
#: largest count as zero (evo uses an absolute machine-epsilon threshold instead).
RANK_RTOL = 1e-12
#: Stricter threshold for reports: below it the rotation about the main direction
#: of travel is so weakly determined (a short, nearly straight run) that Umeyama
#: returns arbitrary roll angles; e.g. KITTI 00 frames 0-15 give 3e-7.
WELL_CONDITIONED_RTOL = 1e-4


def umeyama(
    src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False, *, rank_rtol: float = RANK_RTOL
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ~ s R src + t`` between matched (N,3) point sets.

    Returns ``(R (3,3), t (3,) in dst units (m), s)``; ``s = 1.0`` unless
    ``with_scale``. Raises ``InputError`` when the points are degenerate: fewer
    than 3, or the second singular value of the cross-covariance at most
    ``rank_rtol`` times the first (all on one line: the rotation about that line
    is undetermined).
    """
    src = np.asarray(src_xyz, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst_xyz, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise InputError(None, f"Umeyama alignment needs matched point sets, got {len(src)} and {len(dst)}")
    n = len(src)
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    var_src = float(np.sum(src_c * src_c)) / n if n else 0.0
    cov = dst_c.T @ src_c / max(n, 1)  # (3,3): mean of outer(dst_c, src_c)
    U, d, Vt = np.linalg.svd(cov)
    if n < 3 or d[0] <= 0 or d[1] <= rank_rtol * d[0]:
        ratio = d[1] / d[0] if n >= 3 and d[0] > 0 else 0.0
        raise InputError(
            None,
            f"Umeyama alignment is degenerate for these {n} positions (fewer than 3, or "
            f"(nearly) on one line: singular value ratio {ratio:.2g} <= {rank_rtol:g}); "
            "use origin alignment instead",
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0  # reflection -> proper rotation
    R = U @ S @ Vt
    s = float(np.sum(d * np.diag(S)) / var_src) if with_scale else 1.0
    t = mu_dst - s * (R @ mu_src)
    return R, t, s


def apply_alignment(poses: np.ndarray, R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """Poses ``[R R_i | s R t_i + t]``: scale translations by ``s``, then left-multiply ``[R | t]``."""
    P = np.array(as_poses(poses), dtype=np.float64, copy=True)
    out = np.empty_like(P)
    out[:, :3, :3] = R @ P[:, :3, :3]
    out[:, :3, 3] = s * P[:, :3, 3] @ R.T + t
    out[:, 3] = P[:, 3]
    return out


def _like(traj, poses: np.ndarray):
    if isinstance(traj, Trajectory):
        return Trajectory(poses, None if traj.timestamps is None else traj.timestamps.copy())
    return poses


def align_origin(est, gt):
    """Estimate moved rigidly so its first pose equals GT's first pose.

    Returns ``(aligned, T_gtworld_estworld (4,4))`` with
    ``T = T_world_gt0 @ inv(T_world_est0)``; ``aligned`` is a Trajectory if
    ``est`` is one (timestamps kept), else an (N,4,4) array.
    """
    P, Q = as_poses(est), as_poses(gt)
    if len(P) == 0 or len(Q) == 0:
        raise InputError(None, "origin alignment needs at least one pose in each trajectory")
    T = Q[0] @ geometry.inv(P[0])
    return _like(est, T @ P), T


def align_trajectory(
    est,
    gt,
    correct_scale: bool = False,
    only_first_n: int | None = None,
    *,
    origin: bool = False,
    only_scale: bool = False,
    rank_rtol: float = RANK_RTOL,
):
    """Align ``est`` to ``gt`` (same length, already associated). Returns ``(aligned, T, s)``.

    - default: SE(3) Umeyama on the positions (``correct_scale=True``: Sim(3));
      ``only_first_n`` uses only the first n pose pairs to estimate it (all
      poses are transformed);
    - ``only_scale=True``: Sim(3) Umeyama, but apply only the scale ``s``
      (evo's ``correct_only_scale``);
    - ``origin=True``: first-pose alignment, ``s = 1``.

    ``rank_rtol``: see :func:`umeyama`.

    ``T`` (4,4) is the rigid part ``T_gtworld_estworld``, ``s`` the scale applied
    to the estimate's translations before ``T``. ``aligned`` is a Trajectory if
    ``est`` is one (timestamps kept), else an (N,4,4) array.
    """
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "alignment")
    if origin:
        aligned, T = align_origin(est, gt)
        return aligned, T, 1.0
    n = len(P)
    if only_first_n is not None:
        if not 1 <= int(only_first_n) <= n:
            raise InputError(None, f"only_first_n must be in 1..{n}, got {only_first_n}")
        n = int(only_first_n)
    R, t, s = umeyama(P[:n, :3, 3], Q[:n, :3, 3], with_scale=correct_scale or only_scale, rank_rtol=rank_rtol)
    if only_scale:
        R, t = np.eye(3), np.zeros(3)
    return _like(est, apply_alignment(P, R, t, s)), geometry.make_T(R, t), s
