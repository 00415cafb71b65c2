"""The bench report from its finished cells: Table I (md, csv), Fig. 7, trajectories, JSON.

Table I (SSF-PAN layout): per variant and frontend, for each sequence the RPE over
consecutive frames, translation ``xyz`` (m: RMSE, SSE in m^2, STD) and rotation ``rpy``
(deg: RMSE, SSE in deg^2, STD) -- exactly the ``table1`` numbers of the run's
``metrics.json``, i.e. what ``flowslam eval trajectory_kitti.txt gt_kitti.txt`` prints.
A second table adds APE (m, after SE(3) alignment), KITTI drift (t %, where the path has
100 m segments), ms per frame, frames/s and the cell's peak RSS.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from flowslam.benchmark.suite import VARIANTS, kind_of
from flowslam.results import write_json

STATS = ("rmse", "sse", "std")


def load_cells(bench_dir: Path, sequences, frontends) -> dict[tuple[str, str], dict]:
    from flowslam.benchmark.runner import cell_dir

    cells = {}
    for seq in sequences:
        for fe in frontends:
            path = cell_dir(bench_dir, seq, fe) / "cell.json"
            if path.is_file():
                cells[seq, fe] = json.loads(path.read_text())
    return cells


def _entry(cell: dict | None, variant: str) -> dict:
    """The numbers of one (sequence, frontend, variant); empty values when it did not run."""
    row = (cell or {}).get("rows", {}).get(variant)
    out = {"error": (cell or {}).get("error") or (row or {}).get("error") if cell else "not run"}
    if not row or not row.get("metrics"):
        return out
    m = row["metrics"]
    for part, key in (("xyz", "trans_m"), ("rpy", "rot_deg")):
        for stat in STATS:
            out[f"{part}_{stat}"] = m["table1"][key][stat]
    out.update(
        ape_m=m["ape"]["trans_m"]["rmse"],
        drift_t_percent=m["kitti_drift"]["t_err_percent"],
        ms_per_frame=row["ms_per_frame"],
        fps=1e3 / row["ms_per_frame"] if row["ms_per_frame"] else None,
        peak_rss_mb=cell.get("peak_rss_mb"),
        loops=row["loops"],
        frames=row["frames"],
        run_dir=row["run_dir"],
    )
    objects = cell.get("objects") or {}  # the frontend's, the same for both variants
    out.update(obj_recall=objects.get("recall"), obj_precision=objects.get("precision"),
               obj_speed_error_mps=objects.get("median_speed_error_mps"),
               obj_id_switches_per_100=objects.get("id_switches_per_100_pairs"))
    return out


def table_rows(cells: dict, sequences, frontends) -> list[dict]:
    """One row per (variant, frontend, sequence) with every number (the CSV's rows)."""
    rows = []
    for variant in VARIANTS:
        for fe in frontends:
            for seq in sequences:
                rows.append(dict(variant=variant, frontend=fe, marker=kind_of(fe).marker, kind=kind_of(fe).label,
                                 sequence=seq, **_entry(cells.get((seq, fe)), variant)))
    return rows


def _f(value, digits=3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table1_markdown(rows: list[dict], sequences) -> str:
    """SSF-PAN's Table I layout, then the extra columns (module doc)."""
    by = {(r["variant"], r["frontend"], r["sequence"]): r for r in rows}
    frontends = list(dict.fromkeys(r["frontend"] for r in rows))
    head = ["Framework", "Method"] + [f"{part} {seq} {stat.upper()}" for part in ("xyz", "rpy")
                                      for seq in sequences for stat in STATS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for variant in VARIANTS:
        for fe in frontends:
            cells = []
            for part in ("xyz", "rpy"):
                for seq in sequences:
                    r = by[variant, fe, seq]
                    cells += [_f(r.get(f"{part}_{s}"), 4) for s in STATS]
            name = f"{fe} {kind_of(fe).marker}".strip()
            lines.append(f"| {variant} | {name} | " + " | ".join(cells) + " |")
    extra = ["Framework", "Method"] + [f"{c} {seq}" for seq in sequences
                                       for c in ("APE m", "drift %", "ms/frame", "frames/s", "RSS MB", "loops")]
    lines += ["", "| " + " | ".join(extra) + " |", "|" + "---|" * len(extra)]
    for variant in VARIANTS:
        for fe in frontends:
            cells = []
            for seq in sequences:
                r = by[variant, fe, seq]
                cells += [_f(r.get("ape_m")), _f(r.get("drift_t_percent"), 2), _f(r.get("ms_per_frame"), 0),
                          _f(r.get("fps"), 1), _f(r.get("peak_rss_mb"), 0), str(r.get("loops", "-"))]
            lines.append(f"| {variant} | {fe} | " + " | ".join(cells) + " |")
    lines += _objects_table(by, frontends, sequences)
    notes = sorted({f"{r['frontend']} on {r['sequence']}: {r['error']}" for r in rows if r.get("error")})
    if notes:
        lines += ["", "Not run or stopped early:", ""] + [f"- {n}" for n in notes]
    lines += ["", "Markers (SSF-PAN Table I): ● predicted segmentation and flow; ○ GT flow, predicted "
              "segmentation; ◐ predicted flow, GT segmentation; GT: ground-truth flow (with or without GT "
              "segmentation). xyz in m (SSE m^2), rpy in deg (SSE deg^2)."]
    return "\n".join(lines) + "\n"


def _objects_table(by: dict, frontends: list[str], sequences) -> list[str]:
    """Moving objects per frontend and sequence (a-loam pass; none when no cell has them)."""
    keys = (("obj_recall", "recall"), ("obj_precision", "precision"), ("obj_speed_error_mps", "speed err m/s"),
            ("obj_id_switches_per_100", "ID sw /100"))
    if not any(by["a-loam", fe, seq].get("obj_recall") is not None for fe in frontends for seq in sequences):
        return []
    head = ["Method"] + [f"{label} {seq}" for seq in sequences for _, label in keys]
    lines = ["", "Moving objects (`flowslam flow-eval`'s definitions):", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for fe in frontends:
        cells = [_f(by["a-loam", fe, seq].get(key), 2) for seq in sequences for key, _ in keys]
        lines.append(f"| {fe} | " + " | ".join(cells) + " |")
    return lines


def write_report(bench_dir: Path, sequences: dict, frontends: list[str], info: dict) -> dict:
    """``table1.md``, ``table1.csv``, the plots and ``bench.json`` in ``bench_dir``."""
    from flowslam.benchmark.plots import plot_runtime_vs_rpe, plot_trajectories

    cells = load_cells(bench_dir, sequences, frontends)
    rows = table_rows(cells, list(sequences), frontends)
    (bench_dir / "table1.md").write_text(table1_markdown(rows, list(sequences)))
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with (bench_dir / "table1.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    plot_runtime_vs_rpe(bench_dir / "runtime_vs_rpe.png", rows, list(sequences))
    for seq in sequences:
        plot_trajectories(bench_dir / f"trajectories_{seq}.png", seq, cells, frontends)
    bench = {"info": info, "sequences": {k: str(v) for k, v in sequences.items()}, "frontends": frontends,
             "config": (bench_dir / "config.yaml").read_text(), "rows": rows,
             "cells": {f"{s}/{f}": c for (s, f), c in cells.items()}}
    write_json(bench_dir / "bench.json", bench)
    return bench
