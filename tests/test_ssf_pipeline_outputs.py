"""``ssf`` through the whole pipeline: moving objects written, and ``flow-eval`` on the same loop."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from cli_helpers import assert_one_line_error, flowslam
from flowslam.datasets import open_dataset


@pytest.fixture(scope="module")
def sim_dt(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "dt"
    simulate(out, preset="dt", frames=6, seed=21, sensor="vlp32c")
    return out


def _gt_movers(frame, T_world_sensor, dt):
    """(world centroid, speed m/s) of each GT-dynamic instance of a simulated frame."""
    movers = []
    for i in np.unique(frame.gt_instance[frame.gt_dynamic]):
        m = frame.gt_dynamic & (frame.gt_instance == i)
        c = T_world_sensor[:3, :3] @ frame.points[m].mean(axis=0) + T_world_sensor[:3, 3]
        movers.append((c, np.linalg.norm(frame.extras["flow_compensated"][m].mean(axis=0)) / dt))
    return movers


def test_ssf_run_writes_moving_objects_that_match_the_simulated_movers(sim_dt, tmp_path, one_torch_thread):
    from flowslam.config import load_config
    from flowslam.run import run_sequence

    outcome = run_sequence(sim_dt, load_config(frontend="ssf", output_dir=str(tmp_path)))
    outcome.raise_for_error()
    rows = list(csv.DictReader((outcome.run_dir / "moving_objects.csv").open()))
    ds = open_dataset(sim_dt)
    assert {int(r["frame"]) for r in rows} == set(range(5))  # every scan that has a successor
    for k in range(5):
        biggest = max((r for r in rows if int(r["frame"]) == k), key=lambda r: int(r["n_points"]))
        centroid = np.array([float(biggest[a]) for a in ("cx", "cy", "cz")])
        # world = the first scan's sensor frame, as the simulator's GT poses
        movers = _gt_movers(ds[k], ds.gt_poses[k], ds[k + 1].timestamp - ds[k].timestamp)
        dist = [np.linalg.norm(centroid - c) for c, _ in movers]
        j = int(np.argmin(dist))
        assert dist[j] < 0.5, (k, biggest, dist[j])
        assert abs(float(biggest["speed"]) - movers[j][1]) < 0.5, (k, biggest, movers[j][1])


def test_flow_eval_honours_the_dataset_section_of_the_config(sim_dt, tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"dataset": {"first_frame": 2, "max_frames": 3}}))
    out = tmp_path / "m.json"
    proc = flowslam("flow-eval", "--no-progress", "-f", "gt-flow", "-c", str(config), "--json", str(out), str(sim_dt))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert result["pairs"] == 2  # frames 2, 3, 4
    assert result["flow"]["EPE3D"] < 1e-6  # GT flow against GT flow, on the same points

    config.write_text(yaml.safe_dump({"dataset": {"format": "argoverse2"}}))
    assert_one_line_error(flowslam("flow-eval", "--no-progress", "-f", "gt-flow", "-c", str(config), str(sim_dt)),
                          str(sim_dt))


def test_flow_eval_can_leave_a_warm_up_unscored(sim_dt, tmp_path):
    """``--skip-pairs N``: every frame runs, the first N pairs are not scored; a value that
    leaves no pair is refused before anything runs."""
    out = tmp_path / "m.json"
    proc = flowslam("flow-eval", "--no-progress", "-f", "gt-flow", "--skip-pairs", "2", "--json", str(out), str(sim_dt))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert result["pairs"] == 3 and result["skipped_pairs"] == 2  # 6 frames, 5 pairs, the last 3 scored
    assert result["flow"]["EPE3D"] < 1e-6 and "the first 2 not scored" in " ".join(proc.stdout.split())
    assert_one_line_error(flowslam("flow-eval", "--no-progress", "-f", "gt-flow", "--skip-pairs", "5", str(sim_dt)),
                          "--skip-pairs", "no pair to score")
