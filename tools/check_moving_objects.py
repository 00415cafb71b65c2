"""Do ``ssf``'s moving objects of a real sequence really move? A check by other scans (not a test).

Issue 10 asks to look at what ``ssf`` calls moving on real scans, which have no flow
labels: "parked cars must not move". This script runs the default ``ssf`` frontend over a
sequence and, for each moving instance of scan k-1 with at least ``--min-points`` points
(the car driving ahead included), asks the *other* scans of the sequence, placed in the
world with reference poses (``--poses``; by default ``SEQUENCE/reference_icp_lidar.txt`` as in the
KITTI extract in ``../shared/data``, else the sequence's GT poses, e.g. a simulated one;
only this check uses them, never the frontend):

- **static**: the instance's points where they are (world frame of scan k-1);
- **moved**: the same points carried by the instance's own displacement per scan (the
  world-frame mean of its flow landing minus its points) as many scans forward or back.

For each scan 1 and 2 before and after that is in the sequence, the share of the points
with a point of that scan within ``--radius`` metres, static and moved. The verdict takes
the mean of (moved - static) over those scans: ``moving`` at >= ``--margin``, ``static``
at <= -``--margin``, else ``unclear`` (both fit, e.g. a slide along a wall, or neither:
hidden). A parked car that ``ssf`` moves comes out ``static``.

    python tools/check_moving_objects.py [SEQUENCE] [--poses FILE] [--radius 0.2] [--margin 0.2] [--json OUT]
        [--weights W] [--config RUN.yaml]

``--weights`` runs ``ssf`` with those network weights (e.g. from ``flowslam adapt``)
instead of the shipped ones; ``--config`` with the ``ssf`` section of a run config.

Frames: the reference poses are ``T_world_sensor`` (KITTI layout, one line per scan);
metres.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from flowslam.threads import set_thread_defaults

set_thread_defaults()

import numpy as np  # noqa: E402

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
KITTI = DATA / "kitti-odometry-00-first16"
STEPS = (-2, -1, 1, 2)
"""The other scans asked, relative to scan k-1."""


def instance_checks(frames: list, outputs: list, poses: np.ndarray, radius: float, margin: float,
                    min_points: int) -> list[dict]:
    """One record per moving instance (``outputs[k]``: the frontend's output of pair
    (k-1, k), ``frames[k-1]`` its source scan; ``poses`` (N,4,4) ``T_world_sensor``)."""
    from flowslam.geometry import transform_points
    from flowslam.sceneflow.refinement.clusters import ScanSurface

    world = [transform_points(poses[i], f.points) for i, f in enumerate(frames)]
    surfaces: dict[int, ScanSurface] = {}  # scan j in the world, indexed on first use

    def share(x: np.ndarray, j: int) -> float:
        if j not in surfaces:
            surfaces[j] = ScanSurface(world[j])
        return float(np.mean(surfaces[j].near_any(x, radius)))

    records = []
    for k, out in enumerate(outputs):
        if k == 0 or out is None or out.instance_ids is None or out.flow is None:
            continue
        i = k - 1
        dynamic = ~np.asarray(out.static_mask, dtype=bool)
        ids = np.asarray(out.instance_ids)
        for inst in np.unique(ids[dynamic & (ids >= 0)]):
            m = dynamic & (ids == inst)
            if m.sum() < min_points:
                continue
            p = frames[i].points[m]
            w = world[i][m]
            step = (transform_points(poses[k], p + np.asarray(out.flow)[m]) - w).mean(axis=0)  # world m per scan
            fits = {}
            for dj in STEPS:
                if 0 <= i + dj < len(frames):
                    fits[dj] = (share(w, i + dj), share(w + dj * step, i + dj))
            gain = float(np.mean([moved - still for still, moved in fits.values()])) if fits else 0.0
            verdict = "moving" if gain >= margin else "static" if gain <= -margin else "unclear"
            records.append({
                "scan": i, "instance": int(inst), "points": int(m.sum()),
                "centre_m": p.mean(axis=0).round(2).tolist(), "extent_m": np.ptp(p, axis=0).round(2).tolist(),
                "speed_mps": float(np.linalg.norm(step[:2]) / max(frames[k].timestamp - frames[i].timestamp, 1e-9)),
                "fits": {str(dj): [round(a, 3), round(b, 3)] for dj, (a, b) in fits.items()},
                "gain": round(gain, 3), "verdict": verdict,
            })
    return records


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", default=str(KITTI))
    ap.add_argument("--poses", default=None, help="reference poses (default: SEQUENCE/reference_icp_lidar.txt, "
                                                  "else the sequence's GT poses)")
    ap.add_argument("--radius", type=float, default=0.2)
    ap.add_argument("--margin", type=float, default=0.2)
    ap.add_argument("--min-points", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--weights", default=None, help="network weights of ssf (default: shipped)")
    ap.add_argument("--config", default=None, help="run config YAML whose ssf section replaces the defaults")
    args = ap.parse_args()

    from flowslam.config import load_config
    from flowslam.errors import InputError
    from flowslam.datasets import open_dataset
    from flowslam.frontends.ssf import SsfFrontend
    from flowslam.trajectory import read_trajectory

    sequence = Path(args.sequence)
    dataset = open_dataset(sequence)
    frames = [dataset[i] for i in range(len(dataset))]
    poses_file = Path(args.poses) if args.poses else sequence / "reference_icp_lidar.txt"
    if poses_file.is_file():
        poses, source = read_trajectory(poses_file).poses, str(poses_file)
    elif args.poses is None and dataset.gt_poses is not None:
        poses, source = np.asarray(dataset.gt_poses), "the sequence's GT poses"
    else:
        ap.error(f"{poses_file}: no such poses file (give the sequence's reference poses with --poses)")
    if len(poses) != len(frames):
        ap.error(f"{source}: {len(poses)} poses for the {len(frames)} scans of {sequence}")
    print(f"{sequence}: {len(frames)} scans, reference poses from {source}, weights {args.weights or 'shipped'}")
    try:  # the weights given here override the config's; validated like flowslam run's
        ssf = load_config(args.config, **{"ssf.lookahead": False, "ssf.network.weights": args.weights}).ssf
    except InputError as error:
        ap.error(str(error))
    frontend = SsfFrontend(ssf)
    outputs = [frontend.process(f) for f in frames]
    records = instance_checks(frames, outputs, poses, args.radius, args.margin, args.min_points)
    print(f"{'scan':>4} {'inst':>4} {'pts':>5} {'centre (sensor, m)':>22} {'extent (m)':>18} {'m/s':>5} {'gain':>6}  verdict")
    for r in records:
        print(f"{r['scan']:4d} {r['instance']:4d} {r['points']:5d} {str(r['centre_m']):>22} {str(r['extent_m']):>18} "
              f"{r['speed_mps']:5.1f} {r['gain']:6.2f}  {r['verdict']}")
    counts = {v: sum(r["verdict"] == v for r in records) for v in ("moving", "static", "unclear")}
    print(f"{len(records)} instances of >= {args.min_points} points: {counts}")
    if args.json:
        Path(args.json).write_text(json.dumps({"records": records, "counts": counts}, indent=1))


if __name__ == "__main__":
    main()
