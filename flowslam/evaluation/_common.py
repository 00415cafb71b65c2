"""Shared helpers of the evaluation package: pose stacks, pose-error values, input checks.

Pose errors follow flowslam's convention (``T_a_b`` maps b into a, poses are
``T_world_sensor``). Units: metres and radians; degrees only where a name says so.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from flowslam.errors import InputError
from flowslam.trajectory import Trajectory

__all__ = [
    "POSE_RELATIONS",
    "as_poses",
    "check_same_length",
    "relation_unit",
    "rotation_angle_rad",
    "pose_error_values",
]

#: Pose relations understood by :func:`pose_error_values` (evo's ``PoseRelation``
#: choices, by short name).
POSE_RELATIONS = (
    "translation",  # |t_E| (m)
    "rotation_angle_rad",  # angle of R_E (rad)
    "rotation_angle_deg",  # angle of R_E (deg)
    "rotation_part",  # ||R_E - I||_F (unitless)
    "full",  # ||E - I||_F (unitless)
)

_UNITS = {
    "translation": "m",
    "rotation_angle_rad": "rad",
    "rotation_angle_deg": "deg",
    "rotation_part": "",
    "full": "",
}


def as_poses(traj: Trajectory | np.ndarray) -> np.ndarray:
    """The (N,4,4) float64 ``T_world_sensor`` stack of a Trajectory or of an array."""
    if isinstance(traj, Trajectory):
        return traj.poses
    return np.asarray(traj, dtype=np.float64).reshape(-1, 4, 4)


def check_same_length(est: np.ndarray, gt: np.ndarray, what: str) -> None:
    """Raise ``InputError`` unless the estimate and GT stacks hold the same number of poses."""
    if len(est) != len(gt):
        raise InputError(
            None,
            f"{what}: estimate has {len(est)} poses but ground truth has {len(gt)}; "
            "associate them first (flowslam.evaluation.associate)",
        )
    if len(est) == 0:
        raise InputError(None, f"{what}: the trajectories hold no poses")


def relation_unit(pose_relation: str) -> str:
    """Unit string of an error under ``pose_relation`` (``"m"``, ``"deg"``, ``"rad"`` or ``""``)."""
    try:
        return _UNITS[pose_relation]
    except KeyError:
        raise InputError(
            None, f"unknown pose relation {pose_relation!r}; use one of {', '.join(POSE_RELATIONS)}"
        ) from None


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Rotation angle (rad, in [0, pi]) of (...,3,3) rotations or (...,4,4) transforms.

    Computed as the norm of the rotation vector of scipy's ``Rotation.from_matrix``
    (which projects a slightly non-orthonormal matrix, e.g. KITTI GT printed with 7
    digits, onto SO(3) first). This is the angle evo reports, and it stays accurate
    for tiny angles, unlike ``arccos((tr R - 1) / 2)``.
    """
    R = np.asarray(R, dtype=np.float64)[..., :3, :3]
    flat = R.reshape(-1, 3, 3)
    if len(flat) == 0:
        return np.zeros(R.shape[:-2])
    angles = np.linalg.norm(Rotation.from_matrix(flat).as_rotvec(), axis=-1)
    return angles.reshape(R.shape[:-2])


def pose_error_values(E: np.ndarray, pose_relation: str) -> np.ndarray:
    """Scalar errors of error transforms ``E`` (K,4,4) (identity = no error) under a relation.

    ``translation``: |t_E| (m); ``rotation_angle_rad`` / ``_deg``: angle of R_E;
    ``rotation_part``: ||R_E - I||_F; ``full``: ||E - I||_F.
    """
    relation_unit(pose_relation)  # validates
    E = np.asarray(E, dtype=np.float64).reshape(-1, 4, 4)
    if pose_relation == "translation":
        return np.linalg.norm(E[:, :3, 3], axis=1)
    if pose_relation == "rotation_angle_rad":
        return rotation_angle_rad(E)
    if pose_relation == "rotation_angle_deg":
        return np.rad2deg(rotation_angle_rad(E))
    if pose_relation == "rotation_part":
        return np.linalg.norm(E[:, :3, :3] - np.eye(3), axis=(1, 2))
    return np.linalg.norm(E - np.eye(4), axis=(1, 2))  # full
