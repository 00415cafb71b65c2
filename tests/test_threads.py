"""Thread-pool defaults (``flowslam.threads``): set before the libraries load, the user's wins."""

import json
import os
import subprocess
import sys

from flowslam.threads import CACHE_DEFAULTS, DEFAULTS, set_thread_defaults


def test_defaults_fill_only_what_the_user_left_unset(monkeypatch):
    for name in DEFAULTS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")  # the user's own
    assert set_thread_defaults() == {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_NUM_THREADS": "3",
                                     "ONEDNN_PRIMITIVE_CACHE_CAPACITY": "128", "LRU_CACHE_CAPACITY": "128"}


def test_the_command_sets_them_before_it_runs():
    """A real ``flowslam run --help`` process, started without the variables, has them set."""
    code = ("import json, os\n"
            "from flowslam.cli import app\n"
            "try:\n"
            "    app(['run', '--help'], prog_name='flowslam')\n"
            "except SystemExit:\n"
            "    pass\n"
            f"print(json.dumps({{n: os.environ.get(n) for n in {list(DEFAULTS)!r}}}))")
    assert _fresh_process_json(code, timeout=120) == DEFAULTS


def _fresh_process_json(code: str, env_overrides: dict[str, str] | None = None, timeout: float = 300):
    """The JSON that ``code`` prints last, run in a new Python process whose environment has
    none of the defaults (plus ``env_overrides``)."""
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    env.update(env_overrides or {})
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


CACHE_GROWTH = """
import json, sys
from flowslam.threads import set_thread_defaults
set_thread_defaults()  # before torch loads, as the command does
import torch
from torch import nn
from flowslam.sceneflow.network.backbone import RELU, fusable, linear
from flowslam.sceneflow.network.model import malloc_in_use_bytes

torch.set_num_threads(1)
layer = nn.Linear(9, 16)
with torch.inference_mode():
    x = torch.randn(20300, 9)
    if malloc_in_use_bytes() is None or not fusable(x):
        print(json.dumps(None)); sys.exit()
    for i in range(300):  # the pillar layer's shape: a new row count every call, as every scan brings
        if i == 150:
            start = malloc_in_use_bytes()
        linear(x[:20000 + i], layer, RELU)
print(json.dumps((malloc_in_use_bytes() - start) / 1e6))
"""


def _cache_growth_mb(env_overrides: dict[str, str]) -> float | None:
    """Memory in use (MB, glibc) that 150 fused oneDNN linears of new shapes leave behind
    after 150 others, in a fresh process; None where glibc or the fused kernels are missing."""
    return _fresh_process_json(CACHE_GROWTH, env_overrides)


def test_the_onednn_cache_defaults_stop_the_memory_growing_with_new_shapes():
    """With the defaults, a layer that meets a new row count every call (the network's
    point-count-sized ops, every scan) stops adding to the memory in use once the caches
    are full; with the libraries' own capacities (1,024 shapes) each new shape kept ~0.6 MB."""
    bounded = _cache_growth_mb({})
    if bounded is None:
        import pytest

        pytest.skip("needs glibc's mallinfo2 and torch's fused oneDNN kernels")
    unbounded = _cache_growth_mb({"ONEDNN_PRIMITIVE_CACHE_CAPACITY": "1024", "LRU_CACHE_CAPACITY": "1024"})
    assert bounded < 10.0
    assert unbounded > 40.0  # what the defaults prevent (93 MB measured)


def test_the_network_stage_sets_the_cache_defaults_in_a_program_that_loaded_torch_first():
    """A library user's program (torch imported, no ``set_thread_defaults``) gets the cache
    capacities when it builds the ``ssf`` frontend, before the network's first kernel."""
    code = ("import json, os, torch\n"
            "from flowslam.config import SsfConfig\n"
            "from flowslam.frontends.ssf import SsfFrontend\n"
            "SsfFrontend(SsfConfig())\n"
            f"print(json.dumps({{n: os.environ.get(n) for n in {list(CACHE_DEFAULTS)!r}}}))")
    assert _fresh_process_json(code) == CACHE_DEFAULTS
