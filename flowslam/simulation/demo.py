"""Simulated sequences cached for reuse: the embedded default of ``flowslam demo`` (and
the default suite of ``flowslam bench``), simulated once, then reused.

``ensure_demo_sequence()`` returns the root of a simulated sequence (``manifest.json``,
KITTI layout; ``open_dataset`` reads it): preset ``demo`` (a small procedural town,
250 frames of a 64 x 1024 HDL-64E at 10 Hz, a block loop that comes back to its start,
dt-like traffic with a lead car, no motion distortion), seed ``DEMO_SEED``. It lives in
``<cache>/demo-<hash>``, where ``<cache>`` is ``cache_dir``, else ``$FLOWSLAM_CACHE``,
else ``~/.cache/flowslam``, and ``<hash>`` covers the demo settings and the simulator
version, so a new simulator version simulates a fresh copy. The sequence is written
to a temporary folder and renamed when complete: an interrupted run leaves no
half-written cache behind.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

DEMO_SETTINGS = {"preset": "demo", "seed": 0, "distortion": False}
"""Arguments of ``simulate()`` for the demo (frames, sensor and columns: the preset's)."""


def demo_cache_root(cache_dir: str | Path | None = None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    env = os.environ.get("FLOWSLAM_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "flowslam"


def cached_sequence_path(name: str, settings: dict, cache_dir: str | Path | None = None) -> Path:
    """Where the sequence simulated with ``settings`` (arguments of ``simulate()``) is, or
    will be, cached: ``<cache>/<name>-<hash of the settings and the simulator version>``."""
    from flowslam.simulation.simulator import settings_hash

    return demo_cache_root(cache_dir) / f"{name}-{settings_hash(**settings)}"


def demo_sequence_path(cache_dir: str | Path | None = None) -> Path:
    """Where the demo sequence is (or will be) cached."""
    return cached_sequence_path("demo", DEMO_SETTINGS, cache_dir)


def ensure_demo_sequence(cache_dir: str | Path | None = None, *, refresh: bool = False,
                         progress: Callable[[int, int], None] | None = None) -> Path:
    """The demo sequence's root folder, simulating it first if it is not cached (module doc).

    ``refresh=True`` simulates it again. ``progress(done, total)`` is called per frame
    while simulating (not at all when the cache is used).
    """
    return ensure_sequence("demo", DEMO_SETTINGS, cache_dir, refresh=refresh, progress=progress)


def ensure_sequence(name: str, settings: dict, cache_dir: str | Path | None = None, *, refresh: bool = False,
                    progress: Callable[[int, int], None] | None = None) -> Path:
    """The root folder of the sequence ``simulate(**settings)`` makes, simulating it first
    if it is not cached (written to a temporary folder, renamed when complete)."""
    from flowslam.simulation.simulator import simulate

    target = cached_sequence_path(name, settings, cache_dir)
    if (target / "manifest.json").is_file() and not refresh:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        simulate(tmp, progress=progress, **settings)
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
