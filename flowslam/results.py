"""The results directory of a run: ``OUTPUT_DIR/<date>_<time>_<tag>/`` plus a ``latest`` link.

Files written by ``write_results`` (whatever exists; a failed run still writes
the trajectory of the frames it processed):

- ``trajectory_tum.txt``, ``trajectory_kitti_lidar.txt``: the estimate in the sensor
  frame (``T_world_sensor``, world = first processed scan).
- ``trajectory_kitti.txt``: the estimate in KITTI's convention: camera 0 as KITTI's
  ``poses/XX.txt`` when the input has a KITTI calibration (``T_cam0_sensor``), else the
  sensor frame (:mod:`flowslam.output_files`).
- ``odometry_tum.txt``: the frontend's relative motions chained (no backend).
- ``loops.csv``: accepted loop closures (frames, fitness, RMSE, correction size).
- ``gt_tum.txt``, ``gt_kitti_lidar.txt``, ``gt_kitti.txt``: the dataset's GT for the
  processed frames, in the same frames as the estimate's files of the same suffix.
- ``config.yaml``: the configuration used.
- ``metrics.json``: errors against GT (only when GT exists).
- ``run.json``: what happened (frames, speed, error if any) and ``files``: each file's
  format and frame; written last, so it never claims a file that is not on disk
  (``flowslam.slam.Slam.save``).
- ``trajectory_topview.png``: estimate vs GT, seen from above, with the moving objects' tracks.
- ``static_map.ply``, ``static_map.pcd``: the map (world frame, m; float32 x y z intensity,
  voxel means) from the final poses, without the points the frontend marked dynamic
  (written by ``flowslam.slam``, Open3D tensor IO).
- ``dynamic_points.ply``: the points the frontend marked dynamic (removed from the map),
  world frame with the final poses; x y z, intensity, instance (-1 none), frame.
- ``graph.g2o``: the factor graph of a graph backend (``isam2``) with the final poses
  (see ``flowslam.graph_export``).
- ``moving_objects.csv``: per frame, each moving instance's centroid, velocity, track id and extent
  (world frame; only frontends that give instance ids; objects of tracks seen in at least
  ``output.min_track_scans`` scans).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam import geometry
from flowslam.config import PipelineConfig, dump_config
from flowslam.errors import InputError
from flowslam.output_files import in_kitti_convention
from flowslam.pipeline import RunResult
from flowslam.trajectory import Trajectory, write_kitti, write_tum


def create_results_dir(output_dir: str | Path, tag: str) -> Path:
    """Make a new timestamped run folder ``<date>_<time>_<tag>[_N]`` under ``output_dir``.

    Race-free: two processes starting at the same second get different folders (each
    ``mkdir`` either creates its name or moves on to the next). ``latest`` is left
    alone: :func:`link_latest` moves it once the folder holds a finished run. A folder
    that cannot be made (a file in the way, no permission) is an ``InputError``."""
    output_dir = Path(output_dir)
    safe_tag = re.sub(r"[^A-Za-z0-9._-]+", "-", tag).strip("-")
    stem = f"{datetime.now():%Y-%m-%d_%H-%M-%S}_{safe_tag}"
    try:
        if output_dir.exists() and not output_dir.is_dir():
            raise InputError(output_dir, "output folder is a file, not a folder")
        output_dir.mkdir(parents=True, exist_ok=True)
        for n in itertools.count(1):
            run_dir = output_dir / (stem if n == 1 else f"{stem}_{n}")
            try:
                run_dir.mkdir()
                return run_dir
            except FileExistsError:
                continue
    except OSError as e:
        raise InputError(e.filename or output_dir, f"cannot create the results folder ({_reason(e)})") from None
    raise AssertionError("unreachable")  # pragma: no cover


def make_results_folder(path: str | Path) -> Path:
    """``path`` as a folder (made with its parents if missing); one that cannot be made is
    an ``InputError`` naming it."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(path, f"cannot create the results folder ({_reason(e)})") from None
    return path


def link_latest(run_dir: Path) -> None:
    """Point ``<output_dir>/latest`` at ``run_dir`` (atomically: a new link renamed over
    the old one). Called only once ``run_dir`` holds its ``run.json``."""
    run_dir = Path(run_dir)
    link, tmp = run_dir.parent / "latest", run_dir.parent / f".latest-{os.getpid()}"
    try:
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        tmp.symlink_to(run_dir.name, target_is_directory=True)
        os.replace(tmp, link)
    except OSError as e:
        raise InputError(link, f"cannot update the 'latest' link ({_reason(e)})") from None


def _reason(error: OSError) -> str:
    return error.strerror or str(error)


def write_atomic(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp)`` on a temporary name beside ``path`` (same suffix, so writers
    that pick the format from it still work), then rename it to ``path``: a reader, or
    a run stopped half-way, never sees half a file. ``OSError`` (no space, no
    permission, a file where a folder should be) becomes an ``InputError`` naming
    ``path``; whatever was already written elsewhere stays."""
    path = Path(path)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise InputError(path, f"cannot write ({_reason(e)})") from None
    return path


def write_text(path: str | Path, text: str) -> Path:
    """``text`` into ``path`` through :func:`write_atomic`."""
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")


def write_json(path: str | Path, data: dict) -> Path:
    """``data`` as JSON (numpy values and paths converted), through :func:`write_atomic`."""
    return write_text(path, json.dumps(data, indent=2, default=_json_default, allow_nan=True) + "\n")


def write_loops_csv(path: Path, loops) -> Path:
    """One row per accepted loop: frames i and j, fitness, inlier RMSE (m), and the size of
    the correction it asked for (translation m, rotation deg) from ``info`` where present."""
    rows = ["i,j,fitness,inlier_rmse_m,descriptor_distance,correction_m,correction_deg"]
    for lc in loops:
        rows.append(
            f"{lc.i},{lc.j},{lc.fitness:.4f},{lc.inlier_rmse:.4f},{lc.descriptor_distance:.4f},"
            f"{lc.info.get('correction_m', float('nan')):.4f},{lc.info.get('correction_deg', float('nan')):.4f}"
        )
    return write_text(path, "\n".join(rows) + "\n")


def write_trajectory_files(run_dir: Path, prefix: str, traj: Trajectory,
                           T_cam0_sensor: np.ndarray | None = None) -> list[Path]:
    """``PREFIX_tum.txt`` and ``PREFIX_kitti_lidar.txt`` (sensor frame, ``traj`` as given:
    ``T_world_sensor``) and ``PREFIX_kitti.txt`` in KITTI's convention (camera 0 with
    ``T_cam0_sensor`` = KITTI's ``Tr``, else the sensor frame; :mod:`flowslam.output_files`)."""
    kitti = in_kitti_convention(traj, T_cam0_sensor)
    return [
        write_atomic(run_dir / f"{prefix}_tum.txt", lambda tmp: write_tum(tmp, traj)),
        write_atomic(run_dir / f"{prefix}_kitti.txt", lambda tmp: write_kitti(tmp, kitti)),
        write_atomic(run_dir / f"{prefix}_kitti_lidar.txt", lambda tmp: write_kitti(tmp, traj)),
    ]


def write_results(
    run_dir: Path,
    result: RunResult,
    config: PipelineConfig,
    gt: Trajectory | None,
    metrics: dict | None,
    T_cam0_sensor: np.ndarray | None = None,
    tracks: dict[int, np.ndarray] | None = None,
) -> list[Path]:
    """Write the outputs of a run (see module doc) except ``run.json``, which the caller
    writes last so that it never claims more than is on disk; returns the files
    written. Trajectories first (the most valuable), the top view (when
    ``config.output.plot``) last. Every file goes through :func:`write_atomic`.
    ``T_cam0_sensor``: KITTI's ``Tr`` (4x4, sensor into camera 0) for KITTI input, which
    puts ``trajectory_kitti.txt`` and ``gt_kitti.txt`` in KITTI's camera-0 convention.
    ``tracks``: moving-object tracks to draw on the top view, track id -> (M,3) centroids
    in the world frame of the estimate (m), e.g. ``MovingObjectsLog.tracks``.
    """
    written: list[Path] = []

    def out(name: str, write: Callable[[Path], object]) -> None:
        written.append(write_atomic(run_dir / name, write))

    out("config.yaml", lambda tmp: tmp.write_text(dump_config(config)))
    if len(result.indices):
        est = result.trajectory
        odo = Trajectory(geometry.compose_relatives(result.odometry), est.timestamps)
        written += write_trajectory_files(run_dir, "trajectory", est, T_cam0_sensor)
        out("odometry_tum.txt", lambda tmp: write_tum(tmp, odo))
        if gt is not None:
            written += write_trajectory_files(run_dir, "gt", gt, T_cam0_sensor)
        if result.loops:
            written.append(write_loops_csv(run_dir / "loops.csv", result.loops))
    if metrics is not None:
        written.append(write_json(run_dir / "metrics.json", metrics))
    if config.output.plot and len(result.indices) > 1:
        written.append(_write_top_view(run_dir / "trajectory_topview.png", result, config, gt, tracks))
    return written


def _write_top_view(path: Path, result: RunResult, config: PipelineConfig, gt: Trajectory | None,
                    tracks: dict[int, np.ndarray] | None = None) -> Path:
    from flowslam.plotting import plot_top_view

    position = {index: k for k, index in enumerate(result.indices)}
    loops = [(position[lc.i], position[lc.j]) for lc in result.loops if lc.i in position and lc.j in position]
    odometry = geometry.compose_relatives(result.odometry)
    return write_atomic(path, lambda tmp: plot_top_view(
        tmp, result.poses, None if gt is None else gt.poses,
        title=f"{config.frontend} + {config.backend}", loops=loops, odometry=odometry, tracks=tracks,
    ))
