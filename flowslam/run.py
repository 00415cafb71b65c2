"""``flowslam run`` as a library call: open a sequence, drive a :class:`flowslam.slam.Slam`
over it, write the results folder.

>>> from flowslam.config import load_config
>>> from flowslam.run import run_sequence
>>> outcome = run_sequence("path/to/kitti", load_config())          # doctest: +SKIP
>>> outcome.run_dir, outcome.metrics["rpe"]                          # doctest: +SKIP
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from flowslam.config import PipelineConfig
from flowslam.datasets import frame_range, open_dataset
from flowslam.errors import InputError
from flowslam.interfaces import Frontend
from flowslam.pipeline import RunResult, drive
from flowslam.results import create_results_dir, link_latest, make_results_folder
from flowslam.signals import deferred_signals
from flowslam.slam import Slam
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


OPTION_SECTIONS = {"ssf.network.weights": ("ssf", "--weights")}
"""Options that only some frontends read: dotted config key -> (the config section a
frontend must read, per its ``config_sections``, and the command-line flag)."""


def check_requested_options(config: PipelineConfig, frontend: Frontend, backend, requested: Iterable[str]) -> None:
    """Options the user set explicitly (dotted config keys in ``requested``) that the
    chosen frontend or backend would ignore are an ``InputError``: a run never drops a
    user's choice without a word."""
    requested = set(requested)
    if config.mapping.enabled and "mapping.enabled" in requested and not hasattr(backend, "add_map_factor"):
        raise InputError(None, f"--mapping: backend {config.backend!r} takes no map factors "
                               "(the mapping stage needs a graph backend: -b isam2)")
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
    return make_results_folder(run_dir)


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
    step_listeners: Iterable[Callable] = (),
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
    ``step_listeners`` see every ``flowslam.slam.StepResult`` (e.g. the 3-D recorder
    of ``flowslam.viz.live``). For KITTI input the metrics are those of
    ``trajectory_kitti.txt`` against ``gt_kitti.txt`` (camera 0, as the KITTI devkit).
    """
    dataset = open_dataset(path, config.dataset)
    frames = _frames_to_process(path, dataset, config)
    slam = Slam(config, frontend=frontend, step_listeners=step_listeners)
    check_requested_options(config, slam.frontend, slam.backend, requested)
    timestamped = run_dir is None
    run_dir = _make_run_dir(path, config, tag, run_dir)
    log.info("%s -> %s", dataset.describe(), run_dir)
    if on_start is not None:
        on_start(len(frames))
    result = drive(slam, dataset, frames, on_frame)
    with deferred_signals():
        gt = _ground_truth(dataset, result)
        T_cam0_sensor = getattr(dataset, "T_cam0_velo", None)  # KITTI: files and metrics in camera 0
        metrics = None
        if gt is not None and len(result.indices) >= 2:
            from flowslam.evaluation import evaluate
            from flowslam.output_files import in_kitti_convention

            metrics = evaluate(in_kitti_convention(result.trajectory, T_cam0_sensor),
                               in_kitti_convention(gt, T_cam0_sensor))
        run_info = {"sequence": str(path), "dataset": dataset.describe(), "frontend": config.frontend,
                    "backend": config.backend, "frames_requested": len(frames)}
        slam.save(run_dir, gt=gt, metrics=metrics, run_info=run_info, T_cam0_sensor=T_cam0_sensor)
        if timestamped:
            link_latest(run_dir)
    return RunOutcome(run_dir, result, metrics, dataset.describe())
