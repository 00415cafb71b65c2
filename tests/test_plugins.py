"""Plug-ins by entry point: a third-party package, found on PYTHONPATH through its
``.dist-info`` (what pip installs), adds a frontend and a dataset format that
``flowslam plugins`` lists and ``flowslam run`` uses; a broken one is one error line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tomllib
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_one_line_error

ROOT = Path(__file__).resolve().parents[1]

PLUGIN_MODULE = '''
"""A third-party flowslam plug-in: a frontend that assumes the sensor stands still, and a
reader that keeps every second scan of a KITTI sequence."""
import dataclasses

import numpy as np

from flowslam.datasets import Reader, open_dataset
from flowslam.frame import Dataset
from flowslam.interfaces import FrontendOutput


class StandStill:
    name = "stand-still"

    def process(self, frame):
        first = not hasattr(self, "seen")
        self.seen = True
        return FrontendOutput(frame.index, None if first else np.eye(4), None if first else np.eye(6) * 1e-4)


def make_frontend(config):
    return StandStill()


class EverySecondScan(Dataset):
    name = "every-second"

    def __init__(self, path, **options):
        super().__init__(path)
        self.inner = open_dataset(path, format="kitti", **options)
        self.gt_poses = None if self.inner.gt_poses is None else self.inner.gt_poses[::2]
        self.timestamps = self.inner.timestamps[::2]

    def __len__(self):
        return (len(self.inner) + 1) // 2

    def _load(self, index):
        return dataclasses.replace(self.inner[2 * index], index=index)


READER = Reader(EverySecondScan)
'''

ENTRY_POINTS = """\
[flowslam.frontends]
stand-still = flowslam_standstill:make_frontend
broken = flowslam_standstill_missing:make_frontend
kiss-icp = flowslam_standstill:make_frontend

[flowslam.datasets]
every-second = flowslam_standstill:READER
"""


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory) -> Path:
    """A directory holding the plug-in's module and its installed metadata (dist-info)."""
    site = tmp_path_factory.mktemp("site")
    (site / "flowslam_standstill.py").write_text(textwrap.dedent(PLUGIN_MODULE))
    info = site / "flowslam_standstill-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: flowslam-standstill\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


def flowslam_with(site: Path, *args) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS="240", NO_COLOR="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "flowslam", *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=300)


def test_builtins_are_the_entry_points_of_pyproject():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    installed = entry_points()
    for group in ("flowslam.frontends", "flowslam.backends", "flowslam.datasets"):
        mine = {ep.name: ep.value for ep in installed.select(group=group) if ep.dist.name == "flowslam"}
        assert mine == declared[group], f"{group}: reinstall (pip install -e .) after editing pyproject.toml"


def test_plugins_lists_third_party_with_its_package(plugin_path):
    proc = flowslam_with(plugin_path, "plugins")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    mine = [l for l in lines if l.split()[:1] == ["stand-still"]]
    assert mine and "flowslam-standstill" in mine[0] and "third-party" in mine[0]
    assert any(l.split()[:2] == ["kiss-icp", "flowslam"] and "third-party" not in l for l in lines)
    assert any(l.split()[:1] == ["every-second"] and "third-party" in l for l in lines)
    # a package cannot take a built-in's name
    assert "ignored: 'kiss-icp' of flowslam-standstill" in proc.stderr
    helped = flowslam_with(plugin_path, "run", "--help")
    assert "stand-still" in helped.stdout and "every-second" in helped.stdout


def test_run_with_a_third_party_frontend_and_reader(plugin_path, kitti_extract, tmp_path):
    proc = flowslam_with(plugin_path, "run", "--no-progress", "-f", "stand-still", "-b", "odometry",
                         "--format", "every-second", "-o", tmp_path, kitti_extract)
    assert proc.returncode == 0, proc.stderr
    latest = tmp_path / "latest"
    rows = np.loadtxt(latest / "trajectory_tum.txt")
    assert rows.shape == (8, 8)  # 16 scans, every second one
    np.testing.assert_allclose(rows[:, 1:4], 0, atol=1e-9)  # standing still
    assert json.loads((latest / "run.json").read_text())["frontend"] == "stand-still"


def test_a_broken_plugin_is_one_line_and_spares_the_others(plugin_path, kitti_extract, tmp_path):
    proc = flowslam_with(plugin_path, "run", "--no-progress", "-f", "broken", "-o", tmp_path, kitti_extract)
    assert_one_line_error(proc, "'broken'", "flowslam-standstill", "flowslam_standstill_missing")
    assert not (tmp_path / "latest").exists()
    proc = flowslam_with(plugin_path, "run", "--no-progress", "-n", "2", "-o", tmp_path, kitti_extract)
    assert proc.returncode == 0, proc.stderr
