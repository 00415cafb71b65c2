"""The mapping stage on and off (issue 16): drift, APE, RPE(1) and the stage's time.

Each frontend runs once over the sequence (``isam2``, mapping off), recording its
measurements, points and static masks; the recording is replayed into ``isam2`` with
the mapping stage on, so both rows of a frontend see the very same odometry. Variants:
a-loam (default) or s-loam (``--variant``). Errors against the sequence's GT with
``flowslam.evaluation.evaluate`` (APE after SE(3) alignment, RPE over 1 frame, KITTI drift).

    .venv/bin/python tools/bench_mapping.py SEQ [SEQ...] -f ssf -f kiss-icp [--variant s-loam] \\
        [--set mapping.every=2] [--json out.json]
    .venv/bin/python tools/bench_mapping.py --simulate dt --seed 777 --frames 300 --sensor hdl64 ...

Numbers depend on the machine's load: the stage's time is its median per registered scan.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path

import numpy as np
import yaml


def _run(config, dataset, frontend, frames: int | None = None):
    from flowslam.pipeline import drive
    from flowslam.slam import Slam

    slam = Slam(config, frontend=frontend, outputs=False)
    start = time.perf_counter()
    result = drive(slam, dataset, range(min(len(dataset), frames or len(dataset))), None)
    if result.error is not None:
        raise SystemExit(f"run failed: {result.error}")
    return slam, time.perf_counter() - start


def _row(name, slam, seconds, dataset) -> dict:
    from flowslam.evaluation import evaluate
    from flowslam.trajectory import Trajectory

    est = slam.trajectory()
    m = evaluate(est, Trajectory(np.asarray(dataset.gt_poses)[slam.result().indices], est.timestamps))
    drift = m["kitti_drift"]
    mapping = slam.describe()["mapping"] or {}
    return {"run": name, "rpe1_cm": 100 * m["rpe"][0]["trans_m"]["rmse"], "ape_m": m["ape"]["trans_m"]["rmse"],
            "drift_t_percent": drift["t_err_percent"], "drift_r_deg_per_100m": drift["r_err_deg_per_100m"],
            "end_rot_deg": m["end_point_error"]["rot_deg"], "end_m": m["end_point_error"]["trans_m"],
            "loops": len(slam.result().loops), "map_factors": mapping.get("factors"),
            "map_restarts": mapping.get("restarts"), "mapping_median_ms": mapping.get("median_ms"),
            "seconds": seconds}


def bench(sequence: Path, frontends: list[str], variant: str, settings: dict, cache: Path | None = None,
          frames: int | None = None) -> list[dict]:
    """Rows (mapping off, on) per frontend; ``cache``: keep/reuse each frontend's recording
    there (its seconds are then the replay's, not the frontend's); ``frames``: only the first."""
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.registry import make_frontend
    from flowslam.replay import RecordingFrontend, ReplayFrontend

    dataset = open_dataset(sequence)
    if dataset.gt_poses is None:
        raise SystemExit(f"{sequence}: no GT poses to compare with")
    rows = []
    for name in frontends:
        off = load_config(frontend=name, backend="isam2", variant=variant, **{"mapping.enabled": False})
        on = load_config(frontend=name, backend="isam2", variant=variant, **{"mapping.enabled": True, **settings})
        cached = cache and cache / f"{Path(sequence).name}-{frames or 'all'}-{name}.pkl"
        if cached and cached.exists():  # the frontend's recorded outputs of an earlier run
            replay = pickle.loads(cached.read_bytes())
            slam, seconds = _run(off, dataset, replay, frames)
        else:
            recorder = RecordingFrontend(make_frontend(name, off), per_point=True)
            slam, seconds = _run(off, dataset, recorder, frames)
            replay = ReplayFrontend.of(recorder)
            if cached:
                cached.parent.mkdir(parents=True, exist_ok=True)
                cached.write_bytes(pickle.dumps(replay))
        rows.append(_row(f"{name} {variant}", slam, seconds, dataset))
        slam, seconds = _run(on, dataset, replay, frames)
        rows.append(_row(f"{name} {variant} + mapping", slam, seconds, dataset))
        for row in rows[-2:]:
            print(json.dumps(row), flush=True)
    return rows


def _table(rows: list[dict]) -> str:
    head = "| run | RPE(1) cm | APE m | drift t % | drift °/100 m | end rot ° | map factors | mapping ms |"
    lines = [head, "|" + "---|" * 8]
    for r in rows:
        ms = "" if r["mapping_median_ms"] is None else f"{r['mapping_median_ms']:.1f}"
        fmt = lambda v, f: "" if v is None else format(v, f)  # noqa: E731
        lines.append(f"| {r['run']} | {r['rpe1_cm']:.2f} | {r['ape_m']:.3f} | {fmt(r['drift_t_percent'], '.3f')} | "
                     f"{fmt(r['drift_r_deg_per_100m'], '.3f')} | {r['end_rot_deg']:.2f} | "
                     f"{fmt(r['map_factors'], 'd')} | {ms} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="*", type=Path)
    ap.add_argument("-f", "--frontend", action="append", default=None)
    ap.add_argument("--variant", default="a-loam", choices=("a-loam", "s-loam"))
    ap.add_argument("--set", action="append", default=[], help="mapping option, e.g. mapping.every=2")
    ap.add_argument("--simulate", help="simulate a preset first (into --sim-dir)")
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--sensor", default="hdl64")
    ap.add_argument("--sim-dir", type=Path, default=Path("/tmp/flowslam-bench-mapping"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--max-frames", type=int, help="only the first N frames of each sequence")
    ap.add_argument("--cache", type=Path, help="keep each frontend's recording here and reuse it (tuning runs)")
    args = ap.parse_args()
    settings = {}
    for item in args.set:
        key, _, value = item.partition("=")
        settings[key] = yaml.safe_load(value)
    sequences = list(args.sequences)
    if args.simulate:
        from flowslam.simulation import simulate

        out = args.sim_dir / f"{args.simulate}-{args.seed}-{args.frames}-{args.sensor}"
        if not out.exists():
            simulate(out, preset=args.simulate, frames=args.frames, seed=args.seed, sensor=args.sensor)
        sequences.append(out)
    rows = []
    for seq in sequences:
        print(f"# {seq}", flush=True)
        rows += [dict(r, sequence=str(seq)) for r in bench(seq, args.frontend or ["ssf", "kiss-icp"],
                                                           args.variant, settings, args.cache,
                                                           args.max_frames)]
    print(_table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
