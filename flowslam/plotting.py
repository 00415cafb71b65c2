"""Top-view trajectory plots (PNG), drawn headless with matplotlib's Agg backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_top_view(
    path: str | Path,
    estimate: np.ndarray,
    ground_truth: np.ndarray | None = None,
    title: str = "",
    loops: list[tuple[int, int]] = (),
    odometry: np.ndarray | None = None,
    tracks: dict[int, np.ndarray] | None = None,
) -> Path:
    """Write an x-y top view of ``estimate`` (K,4,4) and optionally ``ground_truth``.

    ``loops`` are (i, j) positions *within* ``estimate`` joined by a red line
    (accepted loop closures); ``odometry`` (K,4,4) is drawn thin for comparison.

    ``tracks``: moving objects, track id -> (M,3) centroids in the estimate's world frame
    (m), drawn as dotted lines coloured by id (20 colours, cycling).

    Both are ``T_world_sensor`` stacks. The estimate is drawn in the GT's world
    frame by anchoring its first pose on the GT's first pose (no other
    alignment, so drift shows as it is). Axes in metres, equal scale.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est = np.asarray(estimate)
    anchor = np.eye(4)
    fig, ax = plt.subplots(figsize=(7, 7), dpi=120)
    if ground_truth is not None and len(ground_truth):
        gt = np.asarray(ground_truth)
        anchor = gt[0] @ np.linalg.inv(est[0])
        ax.plot(gt[:, 0, 3], gt[:, 1, 3], "--", color="0.35", lw=1.5, label="ground truth")
    est = anchor @ est
    if odometry is not None and len(odometry) > 1 and len(loops):
        odo = anchor @ np.asarray(odometry)
        ax.plot(odo[:, 0, 3], odo[:, 1, 3], "-", color="tab:orange", lw=0.8, label="odometry only")
    ax.plot(est[:, 0, 3], est[:, 1, 3], "-", color="tab:blue", lw=1.5, label="estimate")
    for n, (i, j) in enumerate(loops):
        ax.plot(est[[i, j], 0, 3], est[[i, j], 1, 3], "-", color="tab:red", lw=1.0,
                label=f"loop closures ({len(loops)})" if n == 0 else None)
    colours = plt.get_cmap("tab20")
    for n, (track_id, centres) in enumerate(sorted((tracks or {}).items())):
        xy = (np.asarray(centres) @ anchor[:3, :3].T + anchor[:3, 3])[:, :2]
        ax.plot(xy[:, 0], xy[:, 1], ".-", color=colours(track_id % 20), lw=0.8, ms=3,
                label=f"moving objects ({len(tracks)} tracks)" if n == 0 else None)
    ax.plot(est[:1, 0, 3], est[:1, 1, 3], "o", color="tab:green", label="start")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
