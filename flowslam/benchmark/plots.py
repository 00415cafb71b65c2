"""The bench's figures: SSF-PAN Fig. 7 (runtime vs RPE) and the trajectories per sequence.

Top views are x/y of ``T_world_sensor`` (m), world = the first scan; the GT is drawn
from the cell's ``gt_kitti_lidar.txt`` (the same frames, sensor frame).
"""

from __future__ import annotations

from pathlib import Path

from flowslam.benchmark.suite import VARIANTS, kind_of


RPE_FLOOR_M = 1e-4
"""Errors below 0.1 mm (ground-truth flow) are drawn at 0.1 mm, so the log axis stays readable."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_runtime_vs_rpe(path: Path, rows: list[dict], sequences: list[str]) -> None:
    """ms per frame (log) against RPE xyz RMSE (log), one panel per variant and sequence,
    one marker per kind, the < 100 ms (10 Hz) region shaded."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(VARIANTS), len(sequences), figsize=(4.2 * len(sequences), 3.6 * len(VARIANTS)),
                             squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    frontends = list(dict.fromkeys(r["frontend"] for r in rows))
    for i, variant in enumerate(VARIANTS):
        for j, seq in enumerate(sequences):
            ax = axes[i][j]
            ax.axvspan(1e-1, 100.0, color="tab:blue", alpha=0.08, lw=0)
            for n, fe in enumerate(frontends):
                r = next(r for r in rows if (r["variant"], r["sequence"], r["frontend"]) == (variant, seq, fe))
                if r.get("ms_per_frame") is None or not r.get("xyz_rmse"):
                    continue
                k, c = kind_of(fe), colors[n % len(colors)]
                ax.plot(r["ms_per_frame"], max(r["xyz_rmse"], RPE_FLOOR_M), k.plot_marker, ms=9, color=c,
                        mfc=c if k.filled else "none", mew=1.6, label=f"{fe} {k.marker}".strip())
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(left=1.0)
            ax.set_title(f"{seq}, {variant}", fontsize=10)
            ax.set_xlabel("runtime per frame (ms)")
            ax.set_ylabel("RPE xyz RMSE (m)")
            ax.grid(True, which="both", alpha=0.3)
    handles, labels = [], []
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    if labels:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=8, frameon=False)
    fig.suptitle("Runtime vs RPE (shaded: < 100 ms, 10 Hz; errors < 0.1 mm drawn at 0.1 mm)", fontsize=11)
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_trajectories(path: Path, sequence: str, cells: dict, frontends: list[str]) -> None:
    """Every frontend's s-loam trajectory (a-loam when s-loam did not run) over the GT."""
    from flowslam.trajectory import read_trajectory

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 6))
    gt_drawn = False
    for fe in frontends:
        rows = (cells.get((sequence, fe)) or {}).get("rows", {})
        row = rows.get("s-loam") or rows.get("a-loam")
        if not row:
            continue
        run_dir = Path(row["run_dir"])
        if not gt_drawn and (run_dir / "gt_kitti_lidar.txt").is_file():  # sensor frame: x-y is the ground
            gt = read_trajectory(run_dir / "gt_kitti_lidar.txt").poses
            ax.plot(gt[:, 0, 3], gt[:, 1, 3], "--", color="0.3", lw=2.0, label="ground truth")
            gt_drawn = True
        if (run_dir / "trajectory_kitti_lidar.txt").is_file():
            est = read_trajectory(run_dir / "trajectory_kitti_lidar.txt").poses
            ax.plot(est[:, 0, 3], est[:, 1, 3], "-", lw=1.1, label=fe)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{sequence}: trajectories (s-loam), world = first scan")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
