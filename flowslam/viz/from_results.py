"""Build a rerun recording after the fact from a results folder (``flowslam view``).

What is on disk is used as it is (frames: world = the first processed scan's sensor
frame, as every sensor-frame file of the folder; README's output table):
``trajectory_tum.txt`` (poses, timestamps), ``gt_tum.txt`` (anchored to the first
estimated pose), ``loops.csv``, ``static_map.ply``, ``dynamic_points.ply`` (world
points with their scan and instance: the dynamic points of each scan, and the
objects' boxes), ``moving_objects.csv`` (centroids, velocities, track ids). The scans
themselves are re-read from the dataset that ``run.json`` names (with the run's
``config.yaml``), where it can still be opened; a scan point that coincides with one of
``dynamic_points.ply`` is coloured dynamic. Flow vectors are not saved by a run, so only
a live recording (``flowslam run --rerun``) shows them.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError
from flowslam.trajectory import Trajectory, read_trajectory
from flowslam.viz.recorder import DYNAMIC, STATIC, UNLABELLED, RerunRecorder, boxes_of_instances

log = logging.getLogger(__name__)

__all__ = ["record_results", "read_cloud", "log_maps"]

SAME_POINT_M = 0.02
"""A re-read scan point this close to a point of ``dynamic_points.ply`` counts as that point."""


def read_cloud(path: Path) -> dict[str, np.ndarray] | None:
    """The attributes of a PLY/PCD point cloud (``positions`` (N,3), ``instance``, ``frame``,
    ... as (N,) arrays), or None if the file is absent (Open3D's tensor IO)."""
    if not path.is_file():
        return None
    import open3d as o3d

    cloud = o3d.t.io.read_point_cloud(str(path))
    return {key: cloud.point[key].numpy().reshape(len(cloud.point.positions), -1).squeeze(-1)
            if key != "positions" else cloud.point[key].numpy() for key in cloud.point}


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _open_scans(run_dir: Path, run: dict):
    """The run's dataset reopened as the run read it, or None (logged) where it cannot be."""
    sequence = run.get("sequence")
    if not sequence:
        return None
    try:
        from flowslam.config import load_config
        from flowslam.datasets import open_dataset

        config = load_config(run_dir / "config.yaml") if (run_dir / "config.yaml").is_file() else load_config()
        return open_dataset(sequence, config.dataset)
    except (InputError, OSError) as e:
        log.warning("scans not shown: cannot reopen the run's dataset %s (%s)", sequence, e)
        return None


def record_results(run_dir: str | Path, out: str | Path, *, scans: bool = True, **recorder_options) -> Path:
    """Write ``out`` (.rrd) from the results folder ``run_dir`` (module doc); ``scans=False``
    skips re-reading the dataset. ``InputError`` if the folder holds no trajectory."""
    run_dir = Path(run_dir)
    est_path = run_dir / "trajectory_tum.txt"
    if not est_path.is_file():
        raise InputError(run_dir, "not a flowslam results folder (no trajectory_tum.txt)")
    run = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").is_file() else {}
    est = read_trajectory(est_path)
    indices = int(run.get("first_index") or 0) + np.arange(len(est))
    gt = _anchored_gt(run_dir / "gt_tum.txt", est)
    dynamic = read_cloud(run_dir / "dynamic_points.ply")
    objects = _read_csv(run_dir / "moving_objects.csv")
    loops = [(int(r["i"]), int(r["j"])) for r in _read_csv(run_dir / "loops.csv")]
    dataset = _open_scans(run_dir, run) if scans else None

    rec = RerunRecorder(out, **recorder_options)
    for k, index in enumerate(indices):
        rec.pose(index, est.poses[k], None if gt is None else gt.poses[k])
        for i, j in loops:
            if j == index:
                rec.loop(index, i, j)
        dyn = _of_frame(dynamic, index)
        if dataset is not None:
            points = dataset[int(index)].points
            rec.scan(index, est.poses[k], points, _labels(points, est.poses[k], dyn, dynamic is not None))
        elif dyn is not None:
            rec.scan(index, np.eye(4), dyn["positions"], np.full(len(dyn["positions"]), DYNAMIC))
        _log_objects(rec, index, [r for r in objects if int(r["frame"]) == index], dyn)
    rec.final_trajectory(est.poses)
    log_maps(rec, run_dir)
    return rec.close()


def log_maps(rec: RerunRecorder, run_dir: Path) -> None:
    """``static_map.ply`` and ``dynamic_points.ply`` of ``run_dir`` (where present), static."""
    for key, name, labels in (("static_map", "static_map.ply", STATIC), ("dynamic_points", "dynamic_points.ply", DYNAMIC)):
        cloud = read_cloud(Path(run_dir) / name)
        if cloud is not None:
            rec.cloud(key, cloud["positions"], labels=labels)


def _anchored_gt(path: Path, est: Trajectory) -> Trajectory | None:
    """The GT in the estimate's world (first poses anchored together), or None."""
    if not path.is_file():
        return None
    gt = read_trajectory(path)
    if len(gt) != len(est):
        log.warning("%s: %d poses for %d estimated; GT not shown", path, len(gt), len(est))
        return None
    return Trajectory(est.poses[0] @ geometry.inv(gt.poses[0]) @ gt.poses, gt.timestamps)


def _of_frame(cloud: dict | None, index: int) -> dict | None:
    if cloud is None or "frame" not in cloud:
        return None
    own = cloud["frame"] == index
    return {key: value[own] for key, value in cloud.items()} if own.any() else None


def _labels(points: np.ndarray, T_world_sensor: np.ndarray, dyn: dict | None, segmented: bool) -> np.ndarray:
    """STATIC, or DYNAMIC where a point coincides with a dynamic point of its scan;
    UNLABELLED throughout when the run has no segmentation (no ``dynamic_points.ply``)."""
    if dyn is None:
        return np.full(len(points), STATIC if segmented else UNLABELLED)
    from scipy.spatial import cKDTree

    world = geometry.transform_points(T_world_sensor, points)
    near = cKDTree(dyn["positions"]).query(world, distance_upper_bound=SAME_POINT_M)[0]
    return np.where(np.isfinite(near), DYNAMIC, STATIC)


def _log_objects(rec: RerunRecorder, index: int, rows: list[dict], dyn: dict | None) -> None:
    """Boxes from the instance's dynamic points (world axis-aligned), arrows from the CSV."""
    if not rows:
        return
    ids = [int(r["instance_id"]) for r in rows]
    centres = np.array([[float(r[c]) for c in ("cx", "cy", "cz")] for r in rows])
    velocities = np.array([[float(r[c]) for c in ("vx", "vy", "vz")] for r in rows])
    halves = np.full((len(ids), 3), 0.5)
    if dyn is not None and "instance" in dyn:
        box_centres, box_halves = boxes_of_instances(dyn["positions"], dyn["instance"], ids)
        found = box_halves.any(axis=1)
        centres[found], halves[found] = box_centres[found], box_halves[found]
    rec.objects(index, centres, halves, velocities, ids)
