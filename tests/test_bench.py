"""``flowslam bench`` end to end on a tiny simulated sequence: every file, resume after a
kill, and table numbers equal to ``flowslam eval`` on the same trajectories."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from cli_helpers import flowslam

FILES = ("table1.md", "table1.csv", "runtime_vs_rpe.png", "trajectories_tiny.png", "bench.json", "spec.json")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "tiny"
    simulate(out, preset="dt", frames=20, seed=4, sensor="vlp16", columns=360)
    return out


def _bench_dir(results):
    (found,) = [p for p in results.iterdir() if p.name.endswith("_bench")]
    return found


def test_bench_writes_everything_resumes_after_a_kill_and_matches_eval(tiny, tmp_path):
    results = tmp_path / "results"
    cmd = [sys.executable, "-m", "flowslam", "bench", "--no-default-suite", "-s", str(tiny),
           "-f", "gt", "-f", "kiss-icp", "--no-progress", "-o", str(results)]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    first = None
    while time.time() < deadline and proc.poll() is None:
        done = list(results.glob("*_bench/cells/tiny/gt/cell.json"))
        if done:
            first = done[0]
            break
        time.sleep(0.2)
    assert first is not None, proc.communicate()
    os.killpg(proc.pid, signal.SIGKILL)  # the bench and the worker of the second cell
    proc.wait()
    bench_dir = _bench_dir(results)
    assert not (bench_dir / "table1.md").exists()  # it was killed before the report
    stamp = first.stat().st_mtime_ns

    resumed = flowslam("bench", "--resume", str(bench_dir), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert "tiny / gt: done before, kept" in resumed.stdout
    assert first.stat().st_mtime_ns == stamp  # the finished cell was not run again
    for name in FILES:
        assert (bench_dir / name).is_file(), name

    rows = list(csv.DictReader((bench_dir / "table1.csv").open()))
    assert {(r["variant"], r["frontend"]) for r in rows} == {(v, f) for v in ("a-loam", "s-loam")
                                                             for f in ("gt", "kiss-icp")}
    for row in rows:
        run_dir = bench_dir / "cells" / "tiny" / row["frontend"] / row["variant"]
        out = tmp_path / f"{row['frontend']}_{row['variant']}.json"
        ev = flowslam("eval", run_dir / "trajectory_kitti.txt", run_dir / "gt_kitti.txt", "--json", out)
        assert ev.returncode == 0, ev.stderr
        table1 = json.loads(out.read_text())["table1"]
        for part, key in (("xyz", "trans_m"), ("rpy", "rot_deg")):
            for stat in ("rmse", "sse", "std"):
                assert float(row[f"{part}_{stat}"]) == pytest.approx(table1[key][stat], rel=1e-6, abs=1e-6)  # files: ~1e-9 rounding
        assert float(row["ms_per_frame"]) > 0 and float(row["peak_rss_mb"]) > 50
    bench = json.loads((bench_dir / "bench.json").read_text())
    assert bench["frontends"] == ["gt", "kiss-icp"] and "flowslam_version" in bench["info"]
    # moving objects: the GT frontend finds every GT object; KISS-ICP gives no instances
    gt_objects = bench["cells"]["tiny/gt"]["objects"]
    assert gt_objects["recall"] == 1.0 and gt_objects["precision"] == 1.0 and gt_objects["gt_objects"] > 0
    assert bench["cells"]["tiny/kiss-icp"]["objects"] is None
    assert "Moving objects" in (bench_dir / "table1.md").read_text()
    assert (bench_dir / "runtime_vs_rpe.png").read_bytes()[:4] == b"\x89PNG"


def test_bench_refuses_what_it_cannot_run(tmp_path, kitti_extract):
    proc = flowslam("bench", "--no-default-suite", "--no-progress", "-o", tmp_path)
    assert proc.returncode == 2 and "no sequences" in proc.stderr
    proc = flowslam("bench", "--no-default-suite", "-s", kitti_extract, "-f", "nope", "-o", tmp_path)
    assert proc.returncode == 2 and "unknown frontend" in proc.stderr
    # an ablation without the GT it needs is a table entry, not a crash (two cells at once)
    proc = flowslam("bench", "--no-default-suite", "-s", kitti_extract, "-f", "gt", "-f", "kiss-icp", "-j", "2",
                    "--no-progress", "-o", tmp_path)
    assert proc.returncode == 0, proc.stderr
    bench_dir = _bench_dir(tmp_path)
    table = (bench_dir / "table1.md").read_text()
    assert "gt on kitti-odometry-00-first16:" in table and "ground-truth flow" in table
    rows = {(r["variant"], r["frontend"]): r for r in csv.DictReader((bench_dir / "table1.csv").open())}
    assert float(rows["s-loam", "kiss-icp"]["xyz_rmse"]) < 0.2  # KITTI GT: constant-velocity fill, ~0.1 m
    assert json.loads((bench_dir / "bench.json").read_text())["info"]["jobs"] == 2
