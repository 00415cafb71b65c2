"""Shared test fixtures: where the real data in ``../shared/data`` lives.

Set ``FLOWSLAM_DATA`` to point elsewhere. Tests that need a dataset skip with
the reason when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    env = os.environ.get("FLOWSLAM_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def _require(rel: str) -> Path:
    path = shared_data_dir() / rel
    if not path.exists():
        pytest.skip(f"real data not found at {path} (set FLOWSLAM_DATA or place ../shared/data)")
    return path


@pytest.fixture(scope="session")
def kitti_extract() -> Path:
    """KITTI 00 frames 0-15: root with sequences/00 and poses/00.txt."""
    return _require("kitti-odometry-00-first16")


@pytest.fixture(scope="session")
def av2_log() -> Path:
    """The Argoverse 2 sensor log with two sweeps and flow labels."""
    return _require("argoverse2-sensor-val-pair/val/7fab2350-7eaf-3b7e-a39d-6937a4c1bede")


@pytest.fixture(scope="session")
def kitti00_full_gt() -> Path:
    """The full official KITTI 00 GT trajectory (camera-0 frame, KITTI format)."""
    return _require("trajectories/kitti00_gt_poses.txt")


@pytest.fixture
def one_torch_thread():
    """One intra-op torch thread for the test: on a loaded machine two OpenMP threads can wait
    on each other for whole scheduler ticks at every small op, making test times unpredictable."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
