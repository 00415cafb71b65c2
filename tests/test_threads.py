"""Thread-pool defaults (``flowslam.threads``): set before the libraries load, the user's wins."""

import json
import os
import subprocess
import sys

from flowslam.threads import DEFAULTS, set_thread_defaults


def test_defaults_fill_only_what_the_user_left_unset(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")  # the user's own
    assert set_thread_defaults() == {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_NUM_THREADS": "3"}


def test_the_command_sets_them_before_it_runs():
    """A real ``flowslam run --help`` process, started without the variables, has them set."""
    code = ("import json, os\n"
            "from flowslam.cli import app\n"
            "try:\n"
            "    app(['run', '--help'], prog_name='flowslam')\n"
            "except SystemExit:\n"
            "    pass\n"
            f"print(json.dumps({{n: os.environ.get(n) for n in {list(DEFAULTS)!r}}}))")
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == DEFAULTS
