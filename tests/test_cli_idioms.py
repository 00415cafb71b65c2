"""CLI idioms: closed sets are enums whose choices ``--help`` lists (and which match their
source), every command with a progress bar takes ``--no-progress``, a bad command line
is one error line, and ``flowslam --help`` stays light."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cli_helpers import assert_one_line_error, flowslam
from flowslam import cli

BAR_COMMANDS = ["run", "simulate", "demo", "bench", "flow-eval", "train"]


def test_the_enums_match_their_sources():
    from flowslam.config import VARIANTS
    from flowslam.datasets import available_formats
    from flowslam.sceneflow.network.model import PRESETS as MODEL_PRESETS
    from flowslam.simulation import preset_names, sensor_names

    assert [v.value for v in cli.Variant] == list(VARIANTS)
    assert [p.value for p in cli.Preset] == preset_names()
    assert [s.value for s in cli.Sensor] == sensor_names()
    assert [m.value for m in cli.ModelPreset] == list(MODEL_PRESETS)
    assert sorted(f.value for f in cli.DatasetFormat) == sorted(available_formats())


@pytest.mark.parametrize("command, choices", [
    ("run", [*(v.value for v in cli.Variant), *(f.value for f in cli.DatasetFormat)]),
    ("simulate", [*(p.value for p in cli.Preset), *(s.value for s in cli.Sensor)]),
    ("train", [m.value for m in cli.ModelPreset]),
])
def test_help_lists_the_choices(command, choices):
    proc = flowslam(command, "--help")
    assert proc.returncode == 0, proc.stderr
    for choice in choices:
        assert choice in proc.stdout, (command, choice)


def test_frontend_and_backend_help_lists_the_registered_names():
    """The names installed by entry point (the subprocess knows nothing of the names other
    tests register in this process)."""
    from flowslam.registry import entry_point_plugins

    names = [p.name for kind in ("frontend", "backend") for p in entry_point_plugins(kind)]
    assert "kiss-icp" in names and "isam2" in names
    text = flowslam("run", "--help").stdout
    assert [name for name in names if name not in text] == []


@pytest.mark.parametrize("command", BAR_COMMANDS)
def test_every_command_with_a_bar_takes_no_progress(command):
    proc = flowslam(command, "--help")
    assert proc.returncode == 0 and "--no-progress" in proc.stdout, proc.stderr


def test_no_progress_is_accepted_before_any_work(tmp_path):
    # each stops on bad input right after parsing: the option itself was accepted
    assert_one_line_error(flowslam("train", "--no-progress"), "no training data")
    assert_one_line_error(flowslam("flow-eval", "--no-progress", tmp_path / "nope"), "nope")
    assert_one_line_error(flowslam("run", "--no-progress", tmp_path / "nope"), "nope")


def test_a_bad_choice_or_option_is_one_line():
    line = assert_one_line_error(flowslam("run", "--format", "nope", "x"), "'nope'", "kitti", "--format")
    assert "flowslam run --help" in line
    assert_one_line_error(flowslam("simulate", "--sensor", "vlp99", "x"), "vlp99", "vlp16")
    assert_one_line_error(flowslam("run", "--no-such-option", "x"), "--no-such-option")


def test_help_imports_nothing_heavy():
    code = ("import sys, flowslam.cli; "
            "print([m for m in ('torch', 'gtsam', 'open3d', 'kiss_icp') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    assert flowslam("--help").returncode == 0
