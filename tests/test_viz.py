"""The 3-D view: ``flowslam run --rerun`` and ``flowslam view`` write .rrd files that rerun's
own reader (``rerun.chunk.RrdReader``) loads, with the expected entities on one ``frame``
timeline; without rerun-sdk, one line saying how to install it."""

import collections
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from cli_helpers import assert_one_line_error, flowslam

PER_FRAME = ["/world/scan", "/world/sensor", "/world/trajectory/estimate", "/world/trajectory/gt"]


def _frames_by_entity(path: Path) -> dict[str, set]:
    """Entity path -> the ``frame`` values it has data at ("static" for static data)."""
    from rerun.chunk import RrdReader

    found = collections.defaultdict(set)
    for chunk in RrdReader(path).stream().to_chunks():
        if "frame" in chunk.timeline_names:
            found[chunk.entity_path] |= set(chunk.to_record_batch().column("frame").to_pylist())
        else:
            found[chunk.entity_path].add("static")
    return found


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "dt"
    proc = flowslam("simulate", out, "--preset", "dt", "--frames", "5", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def live_run(simulated, tmp_path_factory):
    pytest.importorskip("rerun", reason="rerun-sdk (the viz extra) is not installed: pip install flowslam[viz]")
    out = tmp_path_factory.mktemp("viz")
    proc = flowslam("run", "--no-progress", "-f", "gt", "-o", out / "results", "--rerun", out / "live.rrd", simulated)
    assert proc.returncode == 0, proc.stderr
    return out


def test_live_recording_holds_every_entity_on_one_frame_timeline(live_run):
    proc = subprocess.run([Path(sys.executable).with_name("rerun"), "rrd", "verify", live_run / "live.rrd"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    found = _frames_by_entity(live_run / "live.rrd")
    for entity in PER_FRAME:
        assert set(range(5)) <= found[entity], entity  # every scan
    # the per-point outputs of a step describe the previous scan: frames 0..3 (4 pairs)
    for entity in ("/world/flow", "/world/objects", "/world/objects/velocity"):
        assert set(range(4)) <= found[entity], entity
    for entity in ("/world/static_map", "/world/dynamic_points", "/world/trajectory/final"):
        assert "static" in found[entity], entity


def test_scans_are_coloured_static_and_dynamic(live_run):
    from rerun.chunk import RrdReader

    classes = set()
    for chunk in RrdReader(live_run / "live.rrd").stream().to_chunks():
        if chunk.entity_path == "/world/scan" and "frame" in chunk.timeline_names:
            batch = chunk.to_record_batch()
            column = next(name for name in batch.schema.names if "class_ids" in name)
            for row in batch.column(column).to_pylist():
                classes |= set(row or [])
    assert {1, 2} <= classes  # static and dynamic points in the scans of a frontend with a segmentation


def test_view_builds_one_from_a_results_folder(live_run, tmp_path):
    proc = flowslam("view", live_run / "results" / "latest", "--out", tmp_path / "view.rrd")
    assert proc.returncode == 0, proc.stderr
    found = _frames_by_entity(tmp_path / "view.rrd")
    for entity in PER_FRAME:
        assert set(range(5)) <= found[entity], entity
    assert set(range(4)) <= found["/world/objects"]
    assert "static" in found["/world/static_map"] and "static" in found["/world/dynamic_points"]


def test_without_rerun_one_line_says_how_to_install(tmp_path):
    """rerun hidden from the import system: exit 2 and the install hint, no traceback."""
    script = textwrap.dedent("""
        import sys
        sys.modules["rerun"] = None  # import rerun -> ImportError
        from flowslam.cli import app
        sys.argv = ["flowslam", "view", sys.argv[1]]
        app()
    """)
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert_one_line_error(proc, "pip install flowslam[viz]")
