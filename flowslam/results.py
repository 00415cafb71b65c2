"""The results directory of a run: ``OUTPUT_DIR/<date>_<time>_<tag>/`` plus a ``latest`` link.

Files written by ``write_results`` (whatever exists; a failed run still writes
the trajectory of the frames it processed):

- ``trajectory_tum.txt``, ``trajectory_kitti.txt``: the estimate (``T_world_sensor``,
  world = first processed scan).
- ``odometry_tum.txt``: the frontend's relative motions chained (no backend).
- ``loops.csv``: accepted loop closures (frames, fitness, RMSE, correction size).
- ``gt_tum.txt``, ``gt_kitti.txt``: the dataset's GT for the processed frames.
- ``config.yaml``: the configuration used.
- ``metrics.json``: errors against GT (only when GT exists).
- ``run.json``: what happened (frames, speed, error if any).
- ``trajectory_topview.png``: estimate vs GT, seen from above.
- ``static_map.ply``: the map (world frame, m) from the final poses, without the
  points the frontend marked dynamic (written by ``flowslam.run``).
- ``moving_objects.csv``: per frame, each moving instance's centroid and velocity
  (world frame; only frontends that give instance ids).
"""

from __future__ import annotations

import json
import os
import re
from datetime import datetime
from pathlib import Path

import numpy as np

from flowslam import geometry
from flowslam.config import PipelineConfig, dump_config
from flowslam.pipeline import RunResult
from flowslam.trajectory import Trajectory, write_kitti, write_tum


def create_results_dir(output_dir: str | Path, tag: str) -> Path:
    """Make a new timestamped run folder under ``output_dir`` and point ``latest`` at it."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    safe_tag = re.sub(r"[^A-Za-z0-9._-]+", "-", tag).strip("-")
    stem = f"{datetime.now():%Y-%m-%d_%H-%M-%S}_{safe_tag}"
    run_dir, n = output_dir / stem, 1
    while run_dir.exists():
        n += 1
        run_dir = output_dir / f"{stem}_{n}"
    run_dir.mkdir()
    link, tmp = output_dir / "latest", output_dir / f".latest-{os.getpid()}"
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    tmp.symlink_to(run_dir.name, target_is_directory=True)
    os.replace(tmp, link)
    return run_dir


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")


def write_json(path: Path, data: dict) -> None:
    """``data`` as JSON (numpy values and paths converted), written to a temporary name
    beside ``path`` and renamed, so a reader never sees half a file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=2, default=_json_default, allow_nan=True) + "\n")
    os.replace(tmp, path)


def write_loops_csv(path: Path, loops) -> None:
    """One row per accepted loop: frames i and j, fitness, inlier RMSE (m), and the size of
    the correction it asked for (translation m, rotation deg) from ``info`` where present."""
    rows = ["i,j,fitness,inlier_rmse_m,descriptor_distance,correction_m,correction_deg"]
    for lc in loops:
        rows.append(
            f"{lc.i},{lc.j},{lc.fitness:.4f},{lc.inlier_rmse:.4f},{lc.descriptor_distance:.4f},"
            f"{lc.info.get('correction_m', float('nan')):.4f},{lc.info.get('correction_deg', float('nan')):.4f}"
        )
    path.write_text("\n".join(rows) + "\n")


def write_results(
    run_dir: Path,
    result: RunResult,
    config: PipelineConfig,
    gt: Trajectory | None,
    metrics: dict | None,
    run_info: dict,
) -> list[Path]:
    """Write every output of a run (see module doc); returns the files written. The top
    view is drawn when ``config.output.plot``."""
    written: list[Path] = []

    def out(name: str) -> Path:
        path = run_dir / name
        written.append(path)
        return path

    out("config.yaml").write_text(dump_config(config))
    if len(result.indices):
        est = result.trajectory
        write_tum(out("trajectory_tum.txt"), est)
        write_kitti(out("trajectory_kitti.txt"), est)
        odo = Trajectory(geometry.compose_relatives(result.odometry), est.timestamps)
        write_tum(out("odometry_tum.txt"), odo)
        if gt is not None:
            write_tum(out("gt_tum.txt"), gt)
            write_kitti(out("gt_kitti.txt"), gt)
        position = {index: k for k, index in enumerate(result.indices)}
        loops = [(position[lc.i], position[lc.j]) for lc in result.loops
                 if lc.i in position and lc.j in position]
        if result.loops:
            write_loops_csv(out("loops.csv"), result.loops)
        if config.output.plot and len(est) > 1:
            from flowslam.plotting import plot_top_view

            plot_top_view(
                out("trajectory_topview.png"),
                est.poses,
                None if gt is None else gt.poses,
                title=f"{config.frontend} + {config.backend}",
                loops=loops,
                odometry=odo.poses,
            )
    if metrics is not None:
        write_json(out("metrics.json"), metrics)
    write_json(out("run.json"), run_info)
    return written
