"""The odometry statistics of SSF-PAN's Table I (arXiv:2501.16754, "SSF-PAN: Semantic Scene Flow-Based
Perception for Autonomous Navigation in Traffic Scenarios").

Table I compares odometry by the relative pose error between consecutive
frames (delta = 1 frame, evo's RPE definition ``E = inv(Q_rel) @ P_rel``), with
three statistics each for its translational and rotational part:

- translation ``|t(E)|`` in metres: RMSE (m), SSE (m^2), STD (m);
- rotation angle of ``R(E)`` in degrees: RMSE (deg), SSE (deg^2), STD (deg).

STD is the population standard deviation (evo's). These are exactly the
``rmse`` / ``sse`` / ``std`` fields of ``evo_rpe --delta 1 --delta_unit f``
(``-r trans_part`` and ``-r angle_deg``).
"""

from __future__ import annotations

from ._common import as_poses, check_same_length
from .rpe import pairs_by_index, rpe_errors
from .stats import summary

__all__ = ["table1"]


def table1(est, gt) -> dict:
    """SSF-PAN Table I numbers of associated trajectories.

    Returns ``{"delta_frames": 1, "n_pairs": K, "trans_m": {"rmse", "sse", "std"},
    "rot_deg": {"rmse", "sse", "std"}}`` (``sse`` in m^2 and deg^2); with fewer than
    two poses the statistics are ``None`` and ``n_pairs`` is 0.
    """
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "Table I")
    pairs = pairs_by_index(len(P), 1)
    out = {"delta_frames": 1, "n_pairs": int(len(pairs))}
    for key, relation in (("trans_m", "translation"), ("rot_deg", "rotation_angle_deg")):
        s = summary(rpe_errors(P, Q, pairs, relation))
        out[key] = {"rmse": s["rmse"], "sse": s["sse"], "std": s["std"]}
    return out
