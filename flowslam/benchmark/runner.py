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
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from flowslam import __version__
from flowslam.config import PipelineConfig, dump_config, load_config
from flowslam.errors import InputError

SPEC = "spec.json"


class BenchStopped(RuntimeError):
    """A cell's worker stopped without finishing (killed, crashed): resume to go on."""


def cell_dir(bench_dir: Path, sequence: str, frontend: str) -> Path:
    return bench_dir / "cells" / sequence / frontend


def start_bench(bench_dir: Path, sequences: dict[str, Path], frontends: list[str], config: PipelineConfig) -> None:
    """Write the spec of a new bench into ``bench_dir`` (created)."""
    bench_dir.mkdir(parents=True, exist_ok=True)
    (bench_dir / "config.yaml").write_text(dump_config(config))
    spec = {"sequences": {k: str(v) for k, v in sequences.items()}, "frontends": list(frontends)}
    (bench_dir / SPEC).write_text(json.dumps(spec, indent=1))


def read_spec(bench_dir: Path) -> tuple[dict[str, Path], list[str], PipelineConfig]:
    path = bench_dir / SPEC
    if not path.is_file():
        raise InputError(bench_dir, f"not a bench folder (no {SPEC})")
    spec = json.loads(path.read_text())
    return ({k: Path(v) for k, v in spec["sequences"].items()}, spec["frontends"],
            load_config(bench_dir / "config.yaml"))


def run_bench(bench_dir: Path, *, progress: bool = True, say: Callable[[str], None] = print) -> dict:
    """Run the missing cells of the bench in ``bench_dir``, then write the report; returns
    ``bench.json``'s content."""
    from flowslam.benchmark.report import write_report

    sequences, frontends, _ = read_spec(bench_dir)
    cells = [(s, f) for s in sequences for f in frontends]
    for k, (seq, fe) in enumerate(cells, 1):
        out = cell_dir(bench_dir, seq, fe)
        if (out / "cell.json").is_file():
            say(f"[{k}/{len(cells)}] {seq} / {fe}: done before, kept")
            continue
        say(f"[{k}/{len(cells)}] {seq} / {fe} ...")
        start = time.perf_counter()
        cmd = [sys.executable, "-m", "flowslam.benchmark.worker", "--sequence", str(sequences[seq]),
               "--frontend", fe, "--out", str(out), "--config", str(bench_dir / "config.yaml")]
        if not progress:
            cmd.append("--no-progress")
        proc = subprocess.run(cmd)
        if proc.returncode != 0 or not (out / "cell.json").is_file():
            raise BenchStopped(f"bench cell {seq} / {fe} stopped (exit {proc.returncode}); "
                               f"run `flowslam bench --resume {bench_dir}` to go on")
        cell = json.loads((out / "cell.json").read_text())
        say(f"[{k}/{len(cells)}] {seq} / {fe}: {time.perf_counter() - start:.0f} s"
            + (f" -- not run: {cell['error']}" if cell.get("error") else ""))
    info = {"flowslam_version": __version__, "python": platform.python_version(),
            "machine": platform.machine(), "processor": platform.processor() or None}
    return write_report(bench_dir, sequences, frontends, info)
