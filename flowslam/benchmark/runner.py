"""The benchmark loop: every (sequence, frontend) cell in its own process, resumable.

A bench folder holds ``spec.json`` (sequences, frontends, the configuration file),
``config.yaml``, ``cells/<sequence>/<frontend>/`` (one worker's output, done when its
``cell.json`` exists) and, once every cell is done, the report: ``table1.md``,
``table1.csv``, ``runtime_vs_rpe.png``, ``trajectories_<sequence>.png``, ``bench.json``.
Running the same folder again (``flowslam bench --resume DIR``) skips the finished cells,
so a killed bench picks up where it stopped (the cell that was running starts over).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from flowslam import __version__
from flowslam.config import PipelineConfig, dump_config
from flowslam.errors import InputError

SPEC = "spec.json"


class BenchStopped(RuntimeError):
    """A cell's worker stopped without finishing (killed, crashed): resume to go on."""


def cell_dir(bench_dir: Path, sequence: str, frontend: str) -> Path:
    return bench_dir / "cells" / sequence / frontend


def start_bench(bench_dir: Path, sequences: dict[str, Path], frontends: list[str], config: PipelineConfig,
                jobs: int = 1) -> None:
    """Write the spec of a new bench into ``bench_dir`` (created)."""
    bench_dir.mkdir(parents=True, exist_ok=True)
    (bench_dir / "config.yaml").write_text(dump_config(config))
    spec = {"sequences": {k: str(v) for k, v in sequences.items()}, "frontends": list(frontends), "jobs": jobs}
    (bench_dir / SPEC).write_text(json.dumps(spec, indent=1))


def read_spec(bench_dir: Path) -> tuple[dict[str, Path], list[str], int]:
    """(sequences by name, frontends, jobs) of the bench in ``bench_dir``; the workers read
    its ``config.yaml`` themselves."""
    path = bench_dir / SPEC
    if not path.is_file():
        raise InputError(bench_dir, f"not a bench folder (no {SPEC})")
    spec = json.loads(path.read_text())
    return {k: Path(v) for k, v in spec["sequences"].items()}, spec["frontends"], spec.get("jobs", 1)


def _worker_command(bench_dir: Path, sequence: Path, frontend: str, out: Path, progress: bool) -> list[str]:
    cmd = [sys.executable, "-m", "flowslam.benchmark.worker", "--sequence", str(sequence),
           "--frontend", frontend, "--out", str(out), "--config", str(bench_dir / "config.yaml")]
    return cmd if progress else cmd + ["--no-progress"]


def run_bench(bench_dir: Path, *, progress: bool = True, jobs: int | None = None,
              say: Callable[[str], None] = print) -> dict:
    """Run the missing cells of the bench in ``bench_dir``, ``jobs`` at a time (default:
    the number the bench was started with), then write the report; returns ``bench.json``'s
    content. With ``jobs`` > 1 every worker gets one OpenMP thread (``OMP_NUM_THREADS=1``)
    and no progress bar, and the timings are those of one core per run."""
    from flowslam.benchmark.report import write_report

    sequences, frontends, started_with = read_spec(bench_dir)
    jobs = jobs or started_with
    cells = [(s, f) for s in sequences for f in frontends]
    pending = []
    for k, (seq, fe) in enumerate(cells, 1):
        if (cell_dir(bench_dir, seq, fe) / "cell.json").is_file():
            say(f"[{k}/{len(cells)}] {seq} / {fe}: done before, kept")
        else:
            pending.append((k, seq, fe))
    env = dict(os.environ, OMP_NUM_THREADS="1") if jobs > 1 else None
    running: dict[subprocess.Popen, tuple] = {}
    try:
        while pending or running:
            while pending and len(running) < jobs:
                k, seq, fe = pending.pop(0)
                say(f"[{k}/{len(cells)}] {seq} / {fe} ...")
                out = cell_dir(bench_dir, seq, fe)
                proc = subprocess.Popen(_worker_command(bench_dir, sequences[seq], fe, out, progress and jobs == 1),
                                        env=env)
                running[proc] = (k, seq, fe, out, time.perf_counter())
            finished = [p for p in running if p.poll() is not None]
            if not finished:
                time.sleep(0.2)
                continue
            for proc in finished:
                k, seq, fe, out, start = running.pop(proc)
                if proc.returncode != 0 or not (out / "cell.json").is_file():
                    raise BenchStopped(f"bench cell {seq} / {fe} stopped (exit {proc.returncode}); "
                                       f"run `flowslam bench --resume {bench_dir}` to go on")
                cell = json.loads((out / "cell.json").read_text())
                say(f"[{k}/{len(cells)}] {seq} / {fe}: {time.perf_counter() - start:.0f} s"
                    + (f" -- not run: {cell['error']}" if cell.get("error") else ""))
    finally:
        for proc in running:  # a stop (error, Ctrl-C) takes the running workers with it
            proc.terminate()
            proc.wait()
    info = {"flowslam_version": __version__, "python": platform.python_version(),
            "machine": platform.machine(), "processor": platform.processor() or None,
            "cores": os.cpu_count(), "jobs": jobs}
    return write_report(bench_dir, sequences, frontends, info)
