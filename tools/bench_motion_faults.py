"""Motion faults at a low frame rate: ``ssf`` with motion-fault recovery off vs on, per step.

Simulates a sequence with sharp turns at 2 Hz (20-45 deg per frame,
:func:`flowslam.simulation.ego_path.write_sharp_turn_path`) and runs ``ssf`` (odometry
backend) on it with ``ssf.recovery.enabled`` false (faults detected and counted only)
and true, printing every step's error against the simulator's GT and run.json's
``fallbacks`` entry. Optional checks:

- ``--kiss-icp``: the kiss-icp frontend on the same sequence (it has no recovery);
- ``--kitti DIR``: ``ssf`` + ``isam2`` on the real KITTI extract as ``flowslam run`` does:
  median ms per frame, the recovery stage's own ms per frame, RPE(1) against the ICP
  reference ``reference_icp_lidar.txt``, faults detected (each one a false trigger);
- ``--false-triggers``: short demo-like simulated sequences (``demo``, ``dt``,
  ``rush-hour`` presets at 10 Hz): faults detected (each one a false trigger).

Usage::

    .venv/bin/python tools/bench_motion_faults.py --out /tmp/motion-faults \\
        [--kiss-icp] [--kitti ../shared/data/kitti-odometry-00-first16] [--false-triggers] [--json FILE]

Errors: translation (cm) and rotation (deg) of ``inv(T_gt) @ T`` per step, T = ``T_prev_curr``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from flowslam import geometry

SHARP = dict(preset="static", sensor="hdl64", columns=1024, seed=3)
"""The sharp-turn sequence of the test (tests/test_motion_recovery.py) and of the note."""


def simulate_sharp_turns(out: Path, preset: str = SHARP["preset"], sensor: str = SHARP["sensor"],
                         columns: int = SHARP["columns"], seed: int = SHARP["seed"]) -> Path:
    """The sharp-turn sequence in ``out`` (reused when already there)."""
    from flowslam.simulation import simulate
    from flowslam.simulation.ego_path import SHARP_TURNS_DEG, write_sharp_turn_path

    if (out / "manifest.json").is_file():
        return out
    path = write_sharp_turn_path(out.parent / f"{out.name}_path.tum")
    simulate(out, preset=preset, frames=len(SHARP_TURNS_DEG), seed=seed, sensor=sensor, columns=columns,
             trajectory=path)
    return out


def step_errors(odometry: list[np.ndarray], gt_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-step translation (m) and rotation (deg) error of ``T_prev_curr`` against the GT."""
    t, r = [], []
    for k, T in enumerate(odometry, start=1):
        E = geometry.inv(geometry.relative(gt_poses[k - 1], gt_poses[k])) @ T
        t.append(float(np.linalg.norm(E[:3, 3])))
        r.append(float(np.rad2deg(geometry.rotation_angle(E))))
    return np.array(t), np.array(r)


def run(sequence: Path, out: Path, frontend: str, backend: str = "odometry", **overrides) -> dict:
    """One ``run_sequence``: its run.json, per-step errors (when GT) and the recovery stage's ms."""
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.run import run_sequence

    config = load_config(frontend=frontend, backend=backend, output_dir=str(out), **overrides)
    outcome = run_sequence(sequence, config)
    outcome.raise_for_error()
    info = json.loads((outcome.run_dir / "run.json").read_text())
    result = {"run_dir": str(outcome.run_dir), "median_ms_per_frame": info["median_ms_per_frame"],
              "fallbacks": info["fallbacks"],
              "recovery_ms": [s.get("stage_ms", {}).get("recovery") for s in outcome.result.frontend_stats[1:]]}
    gt = open_dataset(sequence).gt_poses
    if gt is not None:
        t, r = step_errors(outcome.result.odometry, np.asarray(gt)[outcome.result.indices])
        result.update(step_error_cm=np.round(100 * t, 2).tolist(), step_error_deg=np.round(r, 3).tolist())
    result["faults"] = [s.get("recovery", {}).get("faults") for s in outcome.result.frontend_stats[1:]]
    return result


def print_steps(name: str, result: dict, turns_deg: list[float]) -> None:
    print(f"\n{name}: median {result['median_ms_per_frame']:.0f} ms/frame; fallbacks: {result['fallbacks']}")
    print(" step  turn deg   error cm  error deg  faults")
    for k, (turn, e_t, e_r, f) in enumerate(zip(turns_deg, result["step_error_cm"], result["step_error_deg"],
                                                result["faults"]), start=1):
        print(f" {k:4d}  {turn:8.1f}  {e_t:9.2f}  {e_r:9.3f}  {','.join(f) if f else '-'}")
    print(f" worst: {max(result['step_error_cm']):.2f} cm, {max(result['step_error_deg']):.3f} deg")


def kitti_check(kitti: Path, out: Path) -> dict:
    """``ssf`` + ``isam2`` on the KITTI extract: time, RPE(1) against the ICP reference, faults."""
    from flowslam.evaluation import evaluate
    from flowslam.trajectory import read_trajectory

    r = run(kitti, out / "kitti", "ssf", "isam2")
    est = read_trajectory(Path(r["run_dir"]) / "trajectory_kitti_lidar.txt")  # LiDAR frame, as the reference
    metrics = evaluate(est, read_trajectory(kitti / "reference_icp_lidar.txt"))
    rec = [ms for ms in r["recovery_ms"] if ms is not None]
    summary = {"median_ms_per_frame": r["median_ms_per_frame"],
               "recovery_stage_ms_median": statistics.median(rec), "recovery_stage_ms_max": max(rec),
               "rpe1_vs_icp_reference_cm": 100 * metrics["rpe"][0]["trans_m"]["rmse"],
               "faults_detected": r["fallbacks"].get("motion_faults", {}).get("detected"),
               "fallbacks": r["fallbacks"]}
    print(f"\nKITTI extract (ssf + isam2): {json.dumps(summary, indent=1)}")
    return summary


def false_trigger_check(out: Path, frames: int = 30) -> dict:
    """Faults detected by ``ssf`` on short 10 Hz simulated sequences (demo-like presets)."""
    from flowslam.simulation import simulate

    found = {}
    for preset in ("demo", "dt", "rush-hour"):
        seq = out / f"sim_{preset}"
        if not (seq / "manifest.json").is_file():
            simulate(seq, preset=preset, frames=frames, seed=1, sensor="hdl64", columns=1024)
        r = run(seq, out / f"runs_{preset}", "ssf")
        found[preset] = {"faults": r["fallbacks"].get("motion_faults"), "worst_cm": max(r["step_error_cm"]),
                         "median_ms_per_frame": r["median_ms_per_frame"]}
        print(f"\n{preset} ({frames} frames, 10 Hz): {json.dumps(found[preset])}")
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/motion-faults"))
    ap.add_argument("--kiss-icp", action="store_true", help="also the kiss-icp frontend on the sharp turns")
    ap.add_argument("--kitti", type=Path, help="the KITTI extract: time, RPE and false triggers")
    ap.add_argument("--false-triggers", action="store_true", help="demo-like simulated sequences")
    ap.add_argument("--json", type=Path, help="write every number here")
    args = ap.parse_args()
    from flowslam.simulation.ego_path import SHARP_TURNS_DEG

    args.out.mkdir(parents=True, exist_ok=True)
    seq = simulate_sharp_turns(args.out / "sharp_turns")
    turns = list(SHARP_TURNS_DEG[:-1])  # the last pose only gives the last frame's flow
    report: dict = {"sequence": {**SHARP, "turns_deg": turns, "step_m": 3.0, "frame_rate_hz": 2.0}}
    for name, enabled in (("ssf, recovery off", False), ("ssf, recovery on", True)):
        start = time.perf_counter()
        report[name] = run(seq, args.out / "runs", "ssf", **{"ssf.recovery.enabled": enabled})
        report[name]["wall_s"] = time.perf_counter() - start
        print_steps(name, report[name], turns)
    if args.kiss_icp:
        report["kiss-icp"] = run(seq, args.out / "runs", "kiss-icp")
        report["kiss-icp"]["faults"] = [None] * len(turns)
        print_steps("kiss-icp", report["kiss-icp"], turns)
    if args.kitti:
        report["kitti"] = kitti_check(args.kitti, args.out)
    if args.false_triggers:
        report["false_triggers"] = false_trigger_check(args.out)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
