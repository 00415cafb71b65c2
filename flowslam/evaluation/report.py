"""One call for ``flowslam eval``: every metric as a JSON-serialisable dict, and a table.

Units: metres and degrees in the dict (every key carrying a value with a unit
says it: ``*_m``, ``*_deg``, ``*_percent``, ``*_s``); stats dicts are
:func:`~.stats.summary` dicts in the unit of the key that holds them
(``sse`` in the squared unit).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError
from flowslam.trajectory import Trajectory

from ._common import rotation_angle_rad
from .ape import ape_errors
from .align import WELL_CONDITIONED_RTOL, align_origin, align_trajectory
from .associate import associate
from .kitti_drift import KITTI_LENGTHS, kitti_drift
from .rpe import accumulated_distances, rpe_errors, rpe_pairs
from .stats import summary
from .table1 import table1

__all__ = ["evaluate", "render_table"]


def _rpe_entry(P: np.ndarray, Q: np.ndarray, delta, unit: str) -> dict:
    entry = {"delta": delta, "delta_unit": unit, "pairs_from": "gt"}
    pairs = rpe_pairs(Q, delta, unit)  # raises InputError on a bad delta / unit
    entry["n_pairs"] = int(len(pairs))
    entry["trans_m"] = summary(rpe_errors(P, Q, pairs, "translation"))
    entry["rot_deg"] = summary(rpe_errors(P, Q, pairs, "rotation_angle_deg"))
    if len(pairs) == 0:
        entry["note"] = f"no pose pair {delta} {unit} apart along the ground truth"
    return entry


def evaluate(
    est: Trajectory,
    gt: Trajectory,
    *,
    max_diff: float = 0.01,
    offset: float = 0.0,
    rpe_deltas: Iterable[tuple[float, str]] = ((1, "frames"),),
    align: bool = True,
    drift_lengths=KITTI_LENGTHS,
    drift_step: int = 10,
    est_name: str = "estimate",
    gt_name: str = "ground truth",
) -> dict:
    """All metrics of an estimated trajectory against the ground truth.

    Poses are associated first (:func:`~.associate.associate`: by time within
    ``max_diff`` s, ``offset`` s added to the estimate's stamps, or by index).
    APE uses the SE(3) Umeyama-aligned estimate (``align``; falls back to
    origin alignment, with a ``note``, when the positions are (nearly) collinear,
    see ``align.WELL_CONDITIONED_RTOL``: Umeyama's roll about the direction of
    travel is then arbitrary) or the raw one; RPE, KITTI drift and Table I are invariant to a rigid alignment and
    use the raw estimate; RPE pairs are taken along the GT path.

    Returns (all plain Python types)::

        {
          "association": {"method": "timestamps" | "index", "max_diff_s", "offset_s",
                          "n_poses_est", "n_poses_gt", "n_matched"},
          "n_poses_matched": int,
          "path_length_m": float,        # GT, over the matched poses
          "est_path_length_m": float,
          "ape": {"alignment": "SE(3) Umeyama" | "origin" | "none", "scale": 1.0,
                  "T_gt_est": 4x4 nested list (maps estimate world into GT world),
                  "trans_m": stats, "rot_deg": stats[, "note": str]},
          "rpe": [{"delta", "delta_unit": "frames" | "m", "pairs_from": "gt", "n_pairs",
                   "trans_m": stats, "rot_deg": stats[, "note"]}, ...],   # one per rpe_deltas
          "kitti_drift": kitti_drift() dict (t_err_percent, r_err_deg_per_m,
                         r_err_deg_per_100m, n_segments, lengths_m, step_frames, per_length),
          "table1": {"delta_frames": 1, "n_pairs", "trans_m": {"rmse", "sse", "std"},
                     "rot_deg": {"rmse", "sse", "std"}},
          "end_point_error": {"alignment": "origin", "trans_m", "percent_of_path" (None if
                              the GT path is 0 m), "rot_deg"},
        }

    with ``stats = {rmse, mean, median, std, min, max, sse, n}``. Raises
    ``InputError`` for fewer than 2 matched poses or a bad ``rpe_deltas`` entry.
    """
    est_m, gt_m = associate(est, gt, max_diff, offset, est_name=est_name, gt_name=gt_name)
    n = len(est_m)
    if n < 2:
        raise InputError(None, f"only {n} pose of {est_name} matches {gt_name}; need at least 2 to evaluate")
    P, Q = est_m.poses, gt_m.poses
    timed = est.timestamps is not None and gt.timestamps is not None

    # APE: Umeyama SE(3) (or origin) alignment of the positions.
    ape_out: dict = {}
    if align:
        try:
            P_al, T, s = align_trajectory(P, Q, rank_rtol=WELL_CONDITIONED_RTOL)
            ape_out["alignment"] = "SE(3) Umeyama"
        except InputError as e:
            P_al, T, s = align_trajectory(P, Q, origin=True)
            ape_out["alignment"] = "origin"
            ape_out["note"] = f"fell back to origin alignment: {e.problem}"
    else:
        P_al, T, s = P, np.eye(4), 1.0
        ape_out["alignment"] = "none"
    ape_out["scale"] = float(s)
    ape_out["T_gt_est"] = np.asarray(T).tolist()
    ape_out["trans_m"] = summary(ape_errors(P_al, Q, "translation"))
    ape_out["rot_deg"] = summary(ape_errors(P_al, Q, "rotation_angle_deg"))

    rpe_out = []
    for item in rpe_deltas:
        try:
            delta, unit = item
        except (TypeError, ValueError):
            raise InputError(None, f"RPE deltas must be (delta, unit) pairs, got {item!r}") from None
        rpe_out.append(_rpe_entry(P, Q, delta, unit))

    # End point after aligning the first poses: the drift accumulated over the run.
    path_m = float(accumulated_distances(Q[:, :3, 3])[-1])
    P_o, _ = align_origin(P, Q)
    E_end = geometry.inv(P_o[-1]) @ Q[-1]
    end_m = float(np.linalg.norm(P_o[-1, :3, 3] - Q[-1, :3, 3]))
    end = {
        "alignment": "origin",
        "trans_m": end_m,
        "percent_of_path": 100.0 * end_m / path_m if path_m > 0 else None,
        "rot_deg": float(np.rad2deg(rotation_angle_rad(E_end))),
    }

    return {
        "association": {
            "method": "timestamps" if timed else "index",
            "max_diff_s": float(max_diff) if timed else None,
            "offset_s": float(offset) if timed else None,
            "n_poses_est": len(est),
            "n_poses_gt": len(gt),
            "n_matched": n,
        },
        "n_poses_matched": n,
        "path_length_m": path_m,
        "est_path_length_m": float(accumulated_distances(P[:, :3, 3])[-1]),
        "ape": ape_out,
        "rpe": rpe_out,
        "kitti_drift": kitti_drift(P, Q, drift_lengths, drift_step),
        "table1": table1(P, Q),
        "end_point_error": end,
    }


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "-"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


def render_table(metrics: dict, title: str | None = "Trajectory evaluation"):
    """A ``rich.table.Table`` (metric, value, unit) of an :func:`evaluate` dict; metres and degrees."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column("unit")

    def row(name, value, unit="", digits=4):
        table.add_row(name, _fmt(value, digits), unit)

    a = metrics["association"]
    row(f"poses matched ({a['method']})", metrics["n_poses_matched"])
    row("GT path length", metrics["path_length_m"], "m", 2)

    ape = metrics["ape"]
    table.add_section()
    tag = f"APE ({ape['alignment']})"
    for stat in ("rmse", "mean", "median", "std", "max"):
        row(f"{tag} trans {stat}", ape["trans_m"][stat], "m")
    row(f"{tag} rot rmse", ape["rot_deg"]["rmse"], "deg")
    row(f"{tag} rot max", ape["rot_deg"]["max"], "deg")

    for r in metrics["rpe"]:
        table.add_section()
        tag = f"RPE d={r['delta']} {r['delta_unit']} ({r['n_pairs']} pairs)"
        for stat in ("rmse", "mean", "std", "max"):
            row(f"{tag} trans {stat}", r["trans_m"][stat], "m")
        for stat in ("rmse", "mean", "std", "max"):
            row(f"{tag} rot {stat}", r["rot_deg"][stat], "deg")

    k = metrics["kitti_drift"]
    table.add_section()
    row(f"KITTI drift t_err ({k['n_segments']} segments)", k["t_err_percent"], "%", 3)
    row("KITTI drift r_err", k["r_err_deg_per_100m"], "deg/100 m", 3)

    t1 = metrics["table1"]
    table.add_section()
    row("Table I RPE(1) trans RMSE", t1["trans_m"]["rmse"], "m", 5)
    row("Table I RPE(1) trans SSE", t1["trans_m"]["sse"], "m^2", 5)
    row("Table I RPE(1) trans STD", t1["trans_m"]["std"], "m", 5)
    row("Table I RPE(1) rot RMSE", t1["rot_deg"]["rmse"], "deg", 5)
    row("Table I RPE(1) rot SSE", t1["rot_deg"]["sse"], "deg^2", 5)
    row("Table I RPE(1) rot STD", t1["rot_deg"]["std"], "deg", 5)

    e = metrics["end_point_error"]
    table.add_section()
    row("end-point error (origin aligned)", e["trans_m"], "m", 3)
    row("end-point error / path length", e["percent_of_path"], "%", 3)
    row("end-point rotation error", e["rot_deg"], "deg", 3)
    return table
