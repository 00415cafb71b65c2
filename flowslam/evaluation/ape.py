"""Absolute pose error (APE / ATE), with the numbers of evo's ``evo_ape``.

For matched poses ``P_i`` (estimate, after alignment) and ``Q_i`` (GT), both
``T_world_sensor``:

- ``translation``: ``|t(P_i) - t(Q_i)|`` (m), the distance between positions;
- other relations use the error pose ``E_i = inv(P_i) @ Q_i`` (evo's
  ``ape_base``): ``rotation_angle_deg`` / ``_rad`` its rotation angle,
  ``rotation_part`` ``||R_E - I||_F``, ``full`` ``||E - I||_F``.
"""

from __future__ import annotations

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError

from ._common import as_poses, check_same_length, pose_error_values, relation_unit
from .align import align_trajectory
from .stats import summary

__all__ = ["ape_errors", "ape", "alignment_name"]


def ape_errors(est, gt, pose_relation: str = "translation") -> np.ndarray:
    """Per-pose APE (N,) of already aligned, associated poses, in ``relation_unit(pose_relation)``."""
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "APE")
    relation_unit(pose_relation)
    if pose_relation == "translation":
        return np.linalg.norm(P[:, :3, 3] - Q[:, :3, 3], axis=1)
    return pose_error_values(geometry.inv(P) @ Q, pose_relation)


def alignment_name(align: bool, correct_scale: bool, origin: bool) -> str:
    """Human-readable name of an alignment choice, as stored in result dicts."""
    if origin:
        return "origin"
    if align:
        return "Sim(3) Umeyama" if correct_scale else "SE(3) Umeyama"
    return "scale only" if correct_scale else "none"


def ape(
    est,
    gt,
    *,
    align: bool = True,
    correct_scale: bool = False,
    align_origin: bool = False,
    n_to_align: int | None = None,
    pose_relation: str = "translation",
) -> dict:
    """APE statistics of associated trajectories (``Trajectory`` or (N,4,4) arrays).

    Alignment as in ``evo_ape``: ``align`` = Umeyama SE(3) (``-a``), plus
    ``correct_scale`` = Sim(3) (``-as``); ``correct_scale`` alone corrects only
    the scale (``-s``); ``align_origin`` = first poses (``--align_origin``);
    ``n_to_align`` = estimate it from the first n poses only (``--n_to_align``).

    Returns ``{pose_relation, unit, alignment, scale, rmse, mean, median, std,
    min, max, sse, n}`` (statistics in ``unit``: ``"m"``, ``"deg"``, ``"rad"``
    or ``""``; ``sse`` in the squared unit).
    """
    if align and align_origin:
        raise InputError(None, "choose either Umeyama alignment or origin alignment, not both")
    unit = relation_unit(pose_relation)
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "APE")
    s = 1.0
    if align or correct_scale or align_origin:
        P, _, s = align_trajectory(
            P, Q, correct_scale, n_to_align, origin=align_origin, only_scale=correct_scale and not align
        )
    return {
        "pose_relation": pose_relation,
        "unit": unit,
        "alignment": alignment_name(align, correct_scale, align_origin),
        "scale": float(s),
        **summary(ape_errors(P, Q, pose_relation)),
    }
