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
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == DEFAULTS


CACHE_GROWTH = """
import ctypes, json, sys
from flowslam.threads import set_thread_defaults
set_thread_defaults()  # before torch loads, as the command does
import torch
from torch import nn
from flowslam.sceneflow.network.backbone import RELU, fusable, linear

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]

libc = ctypes.CDLL("libc.so.6")
if not hasattr(libc, "mallinfo2"):
    print(json.dumps(None)); sys.exit()
libc.mallinfo2.restype = MallInfo2
torch.set_num_threads(1)
layer = nn.Linear(9, 16)
with torch.inference_mode():
    x = torch.randn(20300, 9)
    if not fusable(x):
        print(json.dumps(None)); sys.exit()
    for i in range(300):  # the pillar layer's shape: a new row count every call, as every scan brings
        if i == 150:
            start = libc.mallinfo2().uordblks
        linear(x[:20000 + i], layer, RELU)
print(json.dumps((libc.mallinfo2().uordblks - start) / 1e6))
"""


def _cache_growth_mb(env_overrides: dict[str, str]) -> float | None:
    """Memory in use (MB, glibc) that 150 fused oneDNN linears of new shapes leave behind
    after 150 others, in a fresh process; None where glibc or the fused kernels are missing."""
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    env.update(env_overrides)
    out = subprocess.run([sys.executable, "-c", CACHE_GROWTH], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


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
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == CACHE_DEFAULTS
