"""Run the real ``flowslam`` command in a subprocess (exit codes and stderr as a user sees them)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np


def flowslam(*args, cwd=None) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS="240", NO_COLOR="1")
    return subprocess.run(
        [sys.executable, "-m", "flowslam", *map(str, args)],
        capture_output=True, text=True, cwd=cwd, env=env, timeout=300,
    )


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """Exit code 2, no traceback, and one ``flowslam: error:`` line holding every needle."""
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    lines = [l for l in proc.stderr.splitlines() if l.startswith("flowslam: error:")]
    assert len(lines) == 1, proc.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def write_kitti_bins(kitti_extract: Path, folder: Path, n: int, every: int = 4) -> list[Path]:
    """Copy the first ``n`` real KITTI scans, keeping every ``every``-th point, as .bin files."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        rec = np.fromfile(kitti_extract / f"sequences/00/velodyne/{i:06d}.bin", dtype=np.float32)
        path = folder / f"{i:06d}.bin"
        rec.reshape(-1, 4)[::every].tofile(path)
        paths.append(path)
    return paths
