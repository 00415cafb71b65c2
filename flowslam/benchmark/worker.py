"""One cell of the benchmark: a frontend over a sequence, both variants, in this process.

The frontend runs once with the ``isam2`` backend and loop closure off (``a-loam``); its
measurements are recorded and replayed into ``isam2`` with loop closure on
(``s-loam``), so both variants see the same odometry. Each variant's run folder is
``<cell>/<variant>/`` (the files of ``flowslam run``); ``<cell>/cell.json`` is written
last, atomically, and marks the cell done.

Timing: ``ms_per_frame`` is a median over the scans (the first scans pay for lazy
imports). For ``a-loam`` it is the run's own wall time per scan (reading, frontend,
iSAM2); for ``s-loam`` the frontend pass plus the replay run's time on the same scan
(reading again, iSAM2, loop detection). ``peak_rss_mb`` is this process's peak resident memory
(both variants; Linux ``ru_maxrss``). ``objects``: the moving-object metrics of the
frontend's outputs in the ``a-loam`` pass (``flowslam.sceneflow.object_metrics``; None
without GT instances or without instances from the frontend).

    python -m flowslam.benchmark.worker --sequence SEQ --frontend NAME --out CELL --config CONFIG.yaml
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

import numpy as np

from flowslam.config import VARIANTS, PipelineConfig, load_config
from flowslam.results import write_json


def _variant_config(config: PipelineConfig, frontend: str, variant: str) -> PipelineConfig:
    cfg = config.model_copy(deep=True, update={"frontend": frontend, "backend": "isam2"})
    cfg.loop_closure.enabled = VARIANTS[variant]
    cfg.output.static_map = False  # the bench compares trajectories; a map per cell costs time
    cfg.output.plot = False
    return cfg


def _row(outcome, per_frame: np.ndarray) -> dict:
    """``per_frame``: the seconds this row spent on each scan (module doc)."""
    result = outcome.result
    n = len(result.indices)
    return {
        "run_dir": str(outcome.run_dir),
        "frames": n,
        "seconds": float(np.sum(per_frame)),
        "ms_per_frame": float(1e3 * np.median(per_frame)) if n else None,
        "loops": len(result.loops),
        "metrics": outcome.metrics,
        "error": None if result.error is None else str(result.error).splitlines()[0],
    }


def _object_scorer(sequence: Path, config: PipelineConfig):
    """A moving-object scorer of the frontend's outputs (``flowslam.flow_eval.FlowEvaluation``
    without the per-point flow arrays) when the sequence has GT poses, else None. Its
    ``objects`` count only where the GT has instances and the frontend gives them."""
    from flowslam.datasets import open_dataset
    from flowslam.flow_eval import FlowEvaluation

    gt_poses = open_dataset(sequence, config.dataset).gt_poses
    return None if gt_poses is None else FlowEvaluation(np.asarray(gt_poses), flow=False)


def run_cell(sequence: Path, frontend: str, cell_dir: Path, config: PipelineConfig, progress=None) -> dict:
    """Run one cell (module doc); returns what ``cell.json`` holds. ``progress(label)``
    may return ``(on_start, on_frame)`` callbacks for a bar."""
    from flowslam.registry import make_frontend
    from flowslam.replay import RecordingFrontend, ReplayFrontend
    from flowslam.run import run_sequence

    cell_dir.mkdir(parents=True, exist_ok=True)
    rows = {}
    start = time.perf_counter()
    cfg = _variant_config(config, frontend, "a-loam")
    recorder = RecordingFrontend(make_frontend(frontend, cfg), per_point=cfg.mapping.enabled)
    on_start, on_frame = progress(f"{frontend} a-loam") if progress else (None, None)
    objects = _object_scorer(sequence, cfg)
    outcome = run_sequence(sequence, cfg, frontend=recorder, run_dir=cell_dir / "a-loam",
                           on_start=on_start, on_frame=on_frame,
                           step_listeners=[lambda step: objects.on_output(step.frame, step.output)] if objects else [])
    frontend_pass = np.asarray(outcome.result.seconds_per_frame)
    rows["a-loam"] = _row(outcome, frontend_pass)
    if outcome.result.indices:
        cfg = _variant_config(config, frontend, "s-loam")
        on_start, on_frame = progress(f"{frontend} s-loam") if progress else (None, None)
        replay = run_sequence(sequence, cfg, frontend=ReplayFrontend.of(recorder),
                              run_dir=cell_dir / "s-loam", on_start=on_start, on_frame=on_frame)
        replayed = np.asarray(replay.result.seconds_per_frame)
        n = min(len(replayed), len(frontend_pass))
        rows["s-loam"] = _row(replay, frontend_pass[:n] + replayed[:n])
    cell = {
        "sequence": str(sequence),
        "frontend": frontend,
        "rows": rows,
        "objects": objects.objects.result() if objects and objects.objects.pairs else None,
        "wall_seconds": time.perf_counter() - start,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    write_json(cell_dir / "cell.json", cell)
    return cell


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="one flowslam bench cell")
    parser.add_argument("--sequence", type=Path, required=True)
    parser.add_argument("--frontend", required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--config", type=Path)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI (before torch loads)
    config = load_config(args.config)
    try:
        if args.no_progress:
            run_cell(args.sequence, args.frontend, args.out, config)
            return
        from flowslam.cli import _progress, _progress_callbacks

        with _progress() as bar:
            run_cell(args.sequence, args.frontend, args.out, config, lambda label: _progress_callbacks(bar, label))
    except Exception as error:  # a cell that cannot run (no GT for an ablation, ...) is a table entry
        args.out.mkdir(parents=True, exist_ok=True)
        write_json(args.out / "cell.json", {
            "sequence": str(args.sequence), "frontend": args.frontend, "rows": {},
            "error": str(error).splitlines()[0] if str(error) else type(error).__name__,
        })


if __name__ == "__main__":  # pragma: no cover
    main()
