"""KITTI odometry drift: the official devkit's segment errors (``evaluate_odometry.cpp``).

Algorithm (Geiger et al., CVPR 2012, devkit ``calcSequenceErrors``), for
index-associated estimate ``P`` and GT ``Q`` (``T_world_sensor``):

1. ``dist[k]``: distance travelled along the **GT** path up to frame k (m).
2. For every first frame ``f = 0, step, 2 step, ...`` (step 10 frames = 1 s at
   10 Hz) and every segment length ``L`` in (100, 200, ..., 800) m, the last
   frame is the first ``l`` with ``dist[l] > dist[f] + L``; segments running past
   the end are skipped.
3. Error of the relative motion ``E = inv(inv(P_f) P_l) @ (inv(Q_f) Q_l)``
   (the inverse of evo's RPE error for the pair ``(f, l)``, so the same
   translation norm and angle); ``t_err = |t_E| / L`` (m/m) and
   ``r_err = acos(clip((tr R_E - 1) / 2)) / L`` (rad/m). The devkit uses general
   matrix inverses (not transposes), so do we. ``L`` is the nominal length, not
   the slightly longer distance actually travelled to frame ``l``.
4. The sequence score is the plain mean over *all* segments (all lengths pooled).

Units reported: ``t_err_percent`` = mean t_err x 100 (%, the devkit's and the
leaderboard's translation number); ``r_err_deg_per_m`` (the leaderboard's
rotation unit, deg/m; the devkit's text output is rad/m) and
``r_err_deg_per_100m`` (= deg/m x 100, the unit most LiDAR-odometry papers
print). Differences to the devkit: float64 instead of float32 distances and
matrices, so segment ends can differ where a distance ties to ~1e-7 m.
"""

from __future__ import annotations

import numpy as np

from flowslam.errors import InputError

from ._common import as_poses, check_same_length
from .rpe import accumulated_distances

__all__ = ["KITTI_LENGTHS", "segment_errors", "kitti_drift"]

#: The devkit's segment lengths (m).
KITTI_LENGTHS = (100, 200, 300, 400, 500, 600, 700, 800)


def segment_errors(est, gt, lengths=KITTI_LENGTHS, step: int = 10) -> dict:
    """Per-segment devkit errors of associated trajectories.

    Returns arrays ``first_frame, last_frame`` (int), ``length_m``, ``t_err``
    (m/m) and ``r_err`` (rad/m), one entry per segment, ordered by first frame
    and then length, as the devkit loops.
    """
    P, Q = as_poses(est), as_poses(gt)
    check_same_length(P, Q, "KITTI drift")
    lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if lengths.size == 0 or np.any(~np.isfinite(lengths)) or np.any(lengths <= 0):
        raise InputError(None, f"KITTI drift segment lengths must be positive metres, got {lengths.tolist()}")
    if int(step) != step or step < 1:
        raise InputError(None, f"KITTI drift step must be a positive number of frames, got {step}")
    dist = accumulated_distances(Q[:, :3, 3])
    first = np.arange(0, len(Q), int(step))
    f = np.repeat(first, len(lengths))
    L = np.tile(lengths, len(first))
    last = np.searchsorted(dist, dist[f] + L, side="right")  # first l with dist[l] > dist[f] + L
    ok = last < len(Q)
    f, last, L = f[ok], last[ok], L[ok]
    delta_gt = np.linalg.inv(Q[f]) @ Q[last]
    delta_est = np.linalg.inv(P[f]) @ P[last]
    E = np.linalg.inv(delta_est) @ delta_gt
    t_err = np.linalg.norm(E[:, :3, 3], axis=1) / L
    cos = 0.5 * (np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1.0)
    r_err = np.arccos(np.clip(cos, -1.0, 1.0)) / L
    return {"first_frame": f, "last_frame": last, "length_m": L, "t_err": t_err, "r_err": r_err}


def _scores(t_err: np.ndarray, r_err: np.ndarray) -> dict:
    if len(t_err) == 0:
        return {"t_err_percent": None, "r_err_deg_per_m": None, "r_err_deg_per_100m": None, "n_segments": 0}
    r_deg_per_m = float(np.rad2deg(np.mean(r_err)))
    return {
        "t_err_percent": float(np.mean(t_err) * 100.0),
        "r_err_deg_per_m": r_deg_per_m,
        "r_err_deg_per_100m": r_deg_per_m * 100.0,
        "n_segments": int(len(t_err)),
    }


def kitti_drift(est, gt, lengths=KITTI_LENGTHS, step: int = 10) -> dict:
    """KITTI devkit drift of associated trajectories (``Trajectory`` or (N,4,4) arrays).

    Returns ``{t_err_percent (%), r_err_deg_per_m, r_err_deg_per_100m, n_segments,
    lengths_m, step_frames, per_length}``; ``per_length`` is a list with one dict
    ``{length_m, t_err_percent, r_err_deg_per_m, r_err_deg_per_100m, n_segments}``
    per segment length. If the GT path is shorter than every length (no segment),
    the error values are ``None`` and ``n_segments`` is 0.
    """
    seg = segment_errors(est, gt, lengths, step)
    lengths = [float(x) for x in np.asarray(lengths, dtype=np.float64).reshape(-1)]
    per_length = []
    for L in lengths:
        sel = seg["length_m"] == L
        per_length.append({"length_m": L, **_scores(seg["t_err"][sel], seg["r_err"][sel])})
    return {
        **_scores(seg["t_err"], seg["r_err"]),
        "lengths_m": lengths,
        "step_frames": int(step),
        "per_length": per_length,
    }
