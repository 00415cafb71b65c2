"""The teacher of ``flowslam adapt``: the full ``ssf`` pipeline (network + test-time
refinement + objects), run once over each sequence and cached on disk.

For every pair (k-1, k) it keeps what the refined pipeline found for the points of
scan k-1: the flow (m, Argoverse 2 convention, sensor frame k), the static mask, the
moving-object instance ids and the odometry step ``T_prev_curr``. The chained steps are the system's *own* pose estimates
(``T_world_sensor``, world = the first scan): the adaptation compensates its inputs
with them exactly as inference does. No ground truth is read.

The cache lives in ``<cache_dir>/teacher-<key>/``, ``key`` a hash of the sequence path,
its first frame, the ``ssf``, ``flow_odometry`` and ``dataset`` options (the frame count
aside) and the weights' hash; a folder without its ``meta.json`` (an interrupted run) is
recomputed. The teacher is causal (pair k sees scans up to k), so a cached run over more
frames of the same sequence serves a shorter one as its prefix (runs that differ only in
``--holdout`` or ``-n`` share one teacher run, and so its exact outputs); a longer run
than the cached one recomputes and replaces it.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam import geometry
from flowslam.config import PipelineConfig
from flowslam.frame import Dataset


@dataclass
class TeacherPair:
    """The refined pipeline's output for the pair (``index - 1``, ``index``)."""

    index: int
    """Dataset index of scan k (the source is the scan before it in the run)."""
    flow: np.ndarray
    """(N,3) float32: flow of scan k-1's points (m, sensor frame k)."""
    static: np.ndarray
    """(N,) bool: static points."""
    instance: np.ndarray
    """(N,) int32: moving-object instance (-1: none)."""
    T_prev_curr: np.ndarray
    """(4,4) the odometry step (scan k into scan k-1's frame)."""

    @property
    def segments(self) -> np.ndarray:
        """(N,) rigid parts for L_mot / L_CD: 0 static, instance + 1 for movers, -1 the
        dynamic points of no instance."""
        seg = np.where(self.static, 0, -1).astype(np.int64)
        moving = ~self.static & (self.instance >= 0)
        seg[moving] = self.instance[moving].astype(np.int64) + 1
        return seg


@dataclass
class Teacher:
    """The teacher's outputs over one sequence."""

    frames: list[int]
    """The dataset indices it ran over, in order."""
    poses: dict[int, np.ndarray]
    """Own ``T_world_sensor`` estimate of every frame (world = ``frames[0]``)."""
    pairs: dict[int, TeacherPair]
    """By the dataset index of scan k."""


def cache_key(path: Path, frames: list[int], config: PipelineConfig, weights_hash: str) -> str:
    """16 hex digits identifying the teacher runs of one sequence from ``frames[0]`` on (of
    any length: :func:`load_teacher` serves a prefix)."""
    dataset = json.loads(config.dataset.model_dump_json())
    dataset.pop("max_frames", None)
    payload = json.dumps({
        "path": str(Path(path).resolve()), "first": frames[0],
        "ssf": json.loads(config.ssf.model_dump_json()), "flow_odometry": json.loads(config.flow_odometry.model_dump_json()),
        "dataset": dataset, "weights": weights_hash,
    }, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _save_pair(folder: Path, pair: TeacherPair) -> None:
    np.savez(folder / f"pair_{pair.index:06d}.npz", flow=pair.flow, static=pair.static, instance=pair.instance,
             T_prev_curr=pair.T_prev_curr)


def _load_pair(file: Path) -> TeacherPair:
    with np.load(file) as z:
        return TeacherPair(int(file.stem.split("_")[1]), z["flow"], z["static"], z["instance"], z["T_prev_curr"])


def load_teacher(folder: Path, frames: list[int] | None = None) -> Teacher | None:
    """The cached teacher in ``folder`` over ``frames`` (all it holds when None), or None
    when it is missing, incomplete or does not start with ``frames``."""
    meta = folder / "meta.json"
    if not meta.is_file():
        return None
    cached = [int(i) for i in json.loads(meta.read_text())["frames"]]
    frames = cached if frames is None else [int(i) for i in frames]
    if cached[:len(frames)] != frames:
        return None
    poses = dict(zip(cached, np.load(folder / "poses.npy")))
    pairs = {index: _load_pair(folder / f"pair_{index:06d}.npz") for index in frames[1:]}
    return Teacher(frames, {i: poses[i] for i in frames}, pairs)


def run_teacher(dataset: Dataset, frames: list[int], config: PipelineConfig, folder: Path,
                on_frame: Callable[[int], None] | None = None) -> Teacher:
    """Run the ``ssf`` frontend of ``config`` (its network weights included) over
    ``frames`` and cache its outputs in ``folder`` (replaced if present)."""
    from flowslam.registry import make_frontend

    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    frontend = make_frontend("ssf", config)
    poses = {frames[0]: np.eye(4)}
    pairs = {}
    prev = frames[0]
    for i, index in enumerate(frames):
        out = frontend.process(dataset[index])
        if i > 0:
            n = len(out.points)
            instance = out.instance_ids if out.instance_ids is not None else np.full(n, -1)
            static = out.static_mask if out.static_mask is not None else np.ones(n, bool)
            pair = TeacherPair(index, np.asarray(out.flow, np.float32), np.asarray(static, bool),
                               np.asarray(instance, np.int32), np.asarray(out.T_prev_curr, np.float64))
            _save_pair(folder, pair)
            pairs[index] = pair
            poses[index] = poses[prev] @ pair.T_prev_curr
            prev = index
        if on_frame is not None:
            on_frame(index)
    np.save(folder / "poses.npy", np.stack([poses[i] for i in frames]))
    (folder / "meta.json").write_text(json.dumps({"frames": frames, "pairs": len(pairs)}))
    return Teacher(frames, poses, pairs)


def ego_flow(pair: TeacherPair, points: np.ndarray) -> np.ndarray:
    """(N,3) the flow the static world has under the teacher's step, for points of scan k-1."""
    return geometry.rigid_flow(geometry.inv(pair.T_prev_curr), points)
