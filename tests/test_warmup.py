"""The set-up's kernel warm-up (``python -m flowslam.warmup``) runs the real pipeline on a
freshly simulated sequence and succeeds (its failure would only be printed by set-up)."""

from __future__ import annotations

import subprocess
import sys


def test_warmup_runs_the_pipeline_on_a_simulated_sequence():
    done = subprocess.run([sys.executable, "-m", "flowslam.warmup"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "kernels compiled and cached" in done.stdout
