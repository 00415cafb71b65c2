"""``flowslam demo``: frontends x backends on the embedded simulated sequence, one table.

The sequence is simulated once into a cache (``flowslam.simulation.demo``). Each
frontend runs once (with the ``odometry`` backend); its measurements are recorded
and *replayed* into every other backend, so all backends see exactly the same
odometry and the demo stays within its time budget. A frontend that cannot run
(e.g. missing weights) is reported in the table, not fatal.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam.config import PipelineConfig
from flowslam.replay import RecordingFrontend, ReplayFrontend

log = logging.getLogger(__name__)

DEMO_FRONTENDS = ("kiss-icp", "ssf", "gt", "gt-flow")
"""The demo's default frontends: the main one, the KISS-ICP baseline and the GT bounds (the
slower baselines and ablations are ``flowslam bench``'s; ``-f`` picks any)."""

DEMO_BACKENDS = ("odometry", "isam2")
"""isam2 runs its default ``s-loam`` variant (``a-loam`` equals ``odometry`` on the same measurements)."""


@dataclass
class DemoRow:
    frontend: str
    backend: str
    metrics: dict | None = None
    seconds: float = float("nan")
    loops: int = 0
    run_dir: Path | None = None
    error: str | None = None
    extra: dict = field(default_factory=dict)


def run_demo(
    sequence: Path,
    config: PipelineConfig,
    frontends: list[str],
    backends: tuple[str, ...] = DEMO_BACKENDS,
    progress: Callable[[str, int], tuple] | None = None,
) -> list[DemoRow]:
    """Run every frontend with every backend on ``sequence``; results under ``config.output_dir``.

    ``progress(label, n)`` may return ``(on_start, on_frame)`` callbacks for a bar.
    """
    from flowslam.registry import make_frontend
    from flowslam.run import run_sequence

    rows: list[DemoRow] = []
    for fe_name in frontends:
        recorder = None
        for be_name in backends:
            cfg = config.model_copy(deep=True, update={"frontend": fe_name, "backend": be_name})
            start = time.perf_counter()
            try:
                if recorder is None:
                    recorder = RecordingFrontend(make_frontend(fe_name, cfg), per_point=cfg.mapping.enabled)
                    frontend = recorder
                else:
                    frontend = ReplayFrontend.of(recorder)
                callbacks = progress(f"{fe_name} + {be_name}", 0) if progress else (None, None)
                outcome = run_sequence(
                    sequence, cfg, frontend=frontend, tag=f"{fe_name}_{be_name}",
                    on_start=callbacks[0], on_frame=callbacks[1],
                )
                outcome.raise_for_error()
            except Exception as error:  # a broken combination (e.g. missing weights) must not end the demo
                log.warning("demo: %s + %s failed: %s", fe_name, be_name, error)
                rows.append(DemoRow(fe_name, be_name, error=str(error).splitlines()[0]))
                if recorder is not None and not recorder.records:
                    break
                continue
            rows.append(DemoRow(
                fe_name, be_name, outcome.metrics, time.perf_counter() - start,
                len(outcome.result.loops), outcome.run_dir,
            ))
    return rows


def _fmt(value, scale=1.0, digits=3) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value * scale:.{digits}f}"


def demo_table(rows: list[DemoRow]):
    """A rich table: APE, RPE(1), KITTI drift, loops, time per combination (failures: see
    ``demo_failures``)."""
    from rich.table import Table

    table = Table(title="flowslam demo: trajectory errors against the simulator's exact GT")
    for col in ["frontend", "backend", "APE m", "RPE1 cm", "RPE1 deg", "drift %", "loops", "s"]:
        table.add_column(col, justify="left" if col in ("frontend", "backend") else "right", no_wrap=True)
    for r in rows:
        m = r.metrics or {}
        rpe = (m.get("rpe") or [{}])[0]
        table.add_row(
            r.frontend, r.backend,
            _fmt(m.get("ape", {}).get("trans_m", {}).get("rmse")),
            _fmt(rpe.get("trans_m", {}).get("rmse"), 100, 2),
            _fmt(rpe.get("rot_deg", {}).get("rmse"), 1, 3),
            _fmt(m.get("kitti_drift", {}).get("t_err_percent"), 1, 2),
            str(r.loops) if r.error is None else "-",
            _fmt(r.seconds, 1, 1),
        )
    return table


def demo_failures(rows: list[DemoRow]) -> list[str]:
    """One line per combination that could not run (printed under the table)."""
    return [f"{r.frontend} + {r.backend}: {r.error}" for r in rows if r.error]
