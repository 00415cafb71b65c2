"""Thread-pool and cache defaults of the native libraries, set before they load (no imports here).

The ``flowslam`` command and the benchmark scripts call :func:`set_thread_defaults` first,
before numpy, torch or Open3D are imported (their thread pools read the environment once,
when they start), so that a benchmark measures what ``flowslam run`` does. A value the
user set in the environment always wins.

- ``OMP_WAIT_POLICY=PASSIVE``: spinning OpenMP threads turned a 0.1 s forward pass into
  seconds when the cores are shared (2-core machines).
- ``OPENBLAS_NUM_THREADS=1``: numpy's OpenBLAS threads spin too, and the wait policy does
  not reach them; one (N,3) @ (3,3) transform of a 124k-point scan took 48 ms under load,
  3 ms on one thread.
- ``ONEDNN_PRIMITIVE_CACHE_CAPACITY=128`` and ``LRU_CACHE_CAPACITY=128`` (the latter is read
  by ideep, torch's oneDNN wrapper): both caches keep what they build for every input shape
  they see, 1,024 shapes by default. The network's point-count-sized ops (the pillar
  PointNet layer, the decoder's GELUs and causal convolution) meet a new shape every scan,
  ~6 primitives per scan, so the memory in use grew ~0.4 MB per scan for ~1,000 scans
  (``docs/sceneflow_evaluation.md``, stop 59). A scan looks up 42 distinct primitives, 36
  of them the same every scan: 128 entries keep those, so they never miss (network stage
  121-130 ms per KITTI pair with either capacity, alternating processes).

Measured and not set: ``OMP_NUM_THREADS=1`` (half the cores on the 2-core VM, so that the
two threads of ``ssf.lookahead`` do not oversubscribe it) changed nothing beyond the
noise, 3.44-3.50 against 3.37-3.60 frames/s end to end (``docs/sceneflow_evaluation.md``).
"""

from __future__ import annotations

import os

__all__ = ["set_thread_defaults", "set_cache_defaults"]

CACHE_DEFAULTS = {"ONEDNN_PRIMITIVE_CACHE_CAPACITY": "128", "LRU_CACHE_CAPACITY": "128"}
"""The oneDNN cache capacities; read when torch runs its first oneDNN kernel, not when it loads."""
DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_NUM_THREADS": "1", **CACHE_DEFAULTS}


def set_thread_defaults() -> dict[str, str]:
    """Set the defaults above where the environment has none; returns the values in effect."""
    return _set_defaults(DEFAULTS)


def set_cache_defaults() -> dict[str, str]:
    """Only the cache capacities: what the ``ssf`` network stage calls when it is built, so
    that a program that loaded torch itself gets them too, unless oneDNN already ran there
    (then its caches keep the capacities they started with)."""
    return _set_defaults(CACHE_DEFAULTS)


def _set_defaults(defaults: dict[str, str]) -> dict[str, str]:
    for name, value in defaults.items():
        os.environ.setdefault(name, value)
    return {name: os.environ[name] for name in defaults}
