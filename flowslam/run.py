"""``flowslam run`` as a library call: open a sequence, run the pipeline, write the results.

>>> from flowslam.config import load_config
>>> from flowslam.run import run_sequence
>>> outcome = run_sequence("path/to/kitti", load_config())          # doctest: +SKIP
>>> outcome.run_dir, outcome.metrics["rpe"]                          # doctest: +SKIP
"""

from __future__ import annotations

import logging
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from flowslam import __version__
from flowslam.config import PipelineConfig
from flowslam.datasets import frame_range, open_dataset
from flowslam.fallbacks import summarize_fallbacks
from flowslam.interfaces import Frontend
from flowslam.loop_closure import make_loop_closer
from flowslam.mapping import StaticMapBuilder
from flowslam.moving_objects import MovingObjectsLog
from flowslam.pipeline import RunResult, run_pipeline
from flowslam.registry import make_backend, make_frontend
from flowslam.errors import InputError
from flowslam.results import create_results_dir, link_latest, write_atomic, write_json, write_results
from flowslam.signals import deferred_signals, describe_stop
from flowslam.trajectory import Trajectory

log = logging.getLogger(__name__)


@dataclass
class RunOutcome:
    run_dir: Path
    result: RunResult
    metrics: dict | None
    dataset_name: str

    def raise_for_error(self) -> None:
        """Re-raise the error that stopped the run early, if any."""
        if self.result.error is not None:
            raise self.result.error


def _ground_truth(dataset, result: RunResult) -> Trajectory | None:
    if dataset.gt_poses is None or not result.indices:
        return None
    return Trajectory(np.asarray(dataset.gt_poses)[result.indices], result.timestamps)


class _OutputSinks:
    """Per-frame consumers of frontend outputs: the static map and the moving objects."""

    def __init__(self, config: PipelineConfig):
        out = config.output
        self.map = (
            StaticMapBuilder(out.map_voxel_size, out.map_points_per_frame) if out.static_map else None
        )
        self.objects = MovingObjectsLog()

    def on_output(self, frame, output) -> None:
        if self.map is not None:
            self.map.on_output(frame, output)
        self.objects.on_output(frame, output)

    def write(self, run_dir: Path, result: RunResult) -> None:
        """``static_map.ply`` and (if any object was seen) ``moving_objects.csv``, with the
        final (optimised) poses of the processed scans."""
        if not result.indices:
            return
        if self.map is not None:
            write_atomic(run_dir / "static_map.ply", lambda tmp: self.map.write(tmp, result.poses, result.indices))
        if self.objects.objects:
            write_atomic(run_dir / "moving_objects.csv",
                         lambda tmp: self.objects.write_csv(tmp, result.poses, result.indices))


OPTION_SECTIONS = {"ssf.network.weights": ("ssf", "--weights")}
"""Options that only some frontends read: dotted config key -> (the config section a
frontend must read, per its ``config_sections``, and the command-line flag)."""


def check_requested_options(config: PipelineConfig, frontend: Frontend, backend, requested: Iterable[str]) -> None:
    """Options the user set explicitly (dotted config keys in ``requested``) that the
    chosen frontend or backend would ignore are an ``InputError``: a run never drops a
    user's choice without a word."""
    requested = set(requested)
    if "loop_closure.enabled" in requested and not getattr(backend, "accepts_loops", False):
        raise InputError(None, f"--variant {config.variant}: backend {config.backend!r} takes no loop closures; "
                               "the variants are of backends that do (-b isam2)")
    sections = set(getattr(frontend, "config_sections", ()))
    for key in sorted(requested & set(OPTION_SECTIONS)):
        section, flag = OPTION_SECTIONS[key]
        if section not in sections:
            raise InputError(None, f"{flag}: frontend {config.frontend!r} does not use it "
                                   f"(it reads {', '.join(sorted(sections)) or 'no options'})")


def _frames_to_process(path, dataset, config: PipelineConfig) -> range:
    frames = frame_range(len(dataset), config.dataset)
    if len(frames) == 0:
        raise InputError(path, f"no frames to process: first frame {config.dataset.first_frame}, "
                               f"but the sequence has {len(dataset)} (0-{len(dataset) - 1})")
    return frames


def _make_run_dir(path, config: PipelineConfig, tag: str | None, run_dir: Path | None) -> Path:
    if run_dir is None:
        return create_results_dir(config.output_dir, tag or f"{Path(path).name}_{config.frontend}_{config.backend}")
    run_dir = Path(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(run_dir, f"cannot create the results folder ({e.strerror or e})") from None
    return run_dir


def run_sequence(
    path: str | Path,
    config: PipelineConfig,
    *,
    on_start: Callable[[int], None] | None = None,
    on_frame: Callable[[int, float], None] | None = None,
    frontend: Frontend | None = None,
    tag: str | None = None,
    run_dir: Path | None = None,
    requested: Iterable[str] = (),
) -> RunOutcome:
    """Run ``config.frontend`` + ``config.backend`` on the sequence at ``path``.

    Always writes the results directory, also when the run stops early on an error
    or a signal (``KeyboardInterrupt``; SIGTERM too inside
    :func:`flowslam.signals.terminate_as_interrupt`): the error is then in
    ``outcome.result.error`` (``outcome.raise_for_error()`` re-raises it). Every file
    is written atomically, ``run.json`` last, and only then does ``latest`` move to
    the folder; SIGINT/SIGTERM arriving while the folder is written are delivered
    after it. Errors before the first scan (a missing path, an unknown frontend, an
    empty frame range, an option in ``requested`` that the chosen parts ignore, see
    :func:`check_requested_options`) raise ``InputError`` before any folder is made.
    ``on_start(n_frames)`` / ``on_frame(k, seconds)`` drive a progress display.
    ``frontend`` overrides ``config.frontend`` with an instance (e.g. a replay of
    recorded measurements); ``tag`` names the results folder; ``run_dir`` (created if
    missing) replaces the timestamped folder and leaves ``latest`` alone.
    """
    dataset = open_dataset(path, config.dataset)
    frames = _frames_to_process(path, dataset, config)
    frontend = frontend or make_frontend(config.frontend, config)
    backend = make_backend(config.backend, config)
    check_requested_options(config, frontend, backend, requested)
    timestamped = run_dir is None
    run_dir = _make_run_dir(path, config, tag, run_dir)
    log.info("%s -> %s", dataset.describe(), run_dir)
    sinks = _OutputSinks(config)
    if on_start is not None:
        on_start(len(frames))
    loop_closer = make_loop_closer(config.loop_closure) if getattr(backend, "accepts_loops", False) else None
    result = run_pipeline(
        dataset, frontend, backend, frames, on_frame,
        loop_closer=loop_closer, on_output=sinks.on_output,
    )
    with deferred_signals():
        gt = _ground_truth(dataset, result)
        metrics = None
        if gt is not None and len(result.indices) >= 2:
            from flowslam.evaluation import evaluate

            metrics = evaluate(result.trajectory, gt)
        write_results(run_dir, result, config, gt, metrics)
        sinks.write(run_dir, result)
        write_json(run_dir / "run.json", _run_info(path, dataset, config, frames, result, backend, loop_closer))
        if timestamped:
            link_latest(run_dir)
    return RunOutcome(run_dir, result, metrics, dataset.describe())


def _run_info(path, dataset, config: PipelineConfig, frames: range, result: RunResult, backend, loop_closer) -> dict:
    """``run.json``: what was asked, what happened (frames, speed, why it stopped)."""
    return {
        "flowslam_version": __version__,
        "python": platform.python_version(),
        "sequence": str(path),
        "dataset": dataset.describe(),
        "frontend": config.frontend,
        "backend": config.backend,
        "loop_closure": loop_closer is not None,
        "frames_requested": len(frames),
        "frames_processed": len(result.indices),
        "first_index": result.indices[0] if result.indices else None,
        "complete": result.error is None,
        "frames_per_second": result.frames_per_second,
        "median_ms_per_frame": float(np.median(result.seconds_per_frame) * 1e3)
        if result.seconds_per_frame else None,
        "error": None if result.error is None else describe_stop(result.error),
        "failed_index": result.failed_index,
        "fallbacks": summarize_fallbacks(result.frontend_stats),
        "loop_closures": len(result.loops),
        "loops": [
            dict(i=lc.i, j=lc.j, fitness=lc.fitness, rmse_m=lc.inlier_rmse, **lc.info)
            for lc in result.loops
        ],
        "backend_stats": getattr(backend, "stats", None),
    }
