#!/usr/bin/env python
"""Benchmark the ``isam2`` backend and the Scan Context loop closer (not a test).

Backend: the official KITTI 00 GT trajectory (4,541 poses, 3.7 km; rotations projected
onto SO(3)) with seeded odometry noise (``--rot-deg`` / ``--trans-m`` 1-sigma per scan,
the same covariance given to the backend) and loop constraints at true revisits: scan j
closes with the nearest scan i at least ``--min-gap`` scans back if it is within
``--radius`` m, at most one loop per ``--every`` scans (GT relative pose plus noise,
covariance 1 deg / 0.1 m). Reports the backend update time per scan (median, p95, max),
the time of the loop updates (loop factor + extra iterations: median, max), the final
batch refinement, the ATE of odometry / iSAM2 online / refined, a-loam's deviation from
the chained odometry, and the process's peak RSS.

Loop closer (``--detector``): the 16 real KITTI scans of the extract cycled along the
same trajectory, each turned by a random yaw so no two are identical, with the descriptor
threshold set so nothing is verified: time per scan (descriptor, voxel cloud, storage,
KD-tree search) and the memory it holds for 4,541 scans; plus the time of ICP
verifications of real pairs (frame 0 against frames 1..15).

    python tools/bench_backend.py [--frames 4541] [--detector] [--seed 0]

Targets: median update <= 5 ms per scan, loop updates <= 50 ms. Exit code 0 if both pass.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

MEDIAN_TARGET_MS = 5.0
LOOP_TARGET_MS = 50.0


def data_dir() -> Path:
    env = os.environ.get("FLOWSLAM_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gt", type=Path, default=data_dir() / "trajectories" / "kitti00_gt_poses.txt")
    ap.add_argument("--frames", type=int, default=None, help="first N poses (default all 4541)")
    ap.add_argument("--rot-deg", type=float, default=0.05, help="odometry rotation noise per scan (deg)")
    ap.add_argument("--trans-m", type=float, default=0.02, help="odometry translation noise per scan (m)")
    ap.add_argument("--radius", type=float, default=5.0, help="revisit radius for loops (m)")
    ap.add_argument("--min-gap", type=int, default=300, help="loops only with scans this many back")
    ap.add_argument("--every", type=int, default=50, help="at most one loop per this many scans")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="Isam2Config override, e.g. --set extra_iterations_after_loop=2 (repeatable)")
    ap.add_argument("--detector", action="store_true", help="also benchmark the Scan Context loop closer")
    return ap.parse_args(argv)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def project_rotations(poses: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    poses = poses.copy()
    poses[:, :3, :3] = U @ Vt
    return poses


def make_scenario(gt: np.ndarray, args: argparse.Namespace):
    """Noisy odometry, its covariance, and loops [(i, j, T_i_j)] at true revisits."""
    from flowslam import geometry

    rng = np.random.default_rng(args.seed)
    sigmas = np.array([np.deg2rad(args.rot_deg)] * 3 + [args.trans_m] * 3)
    rel = geometry.relative(gt[:-1], gt[1:])
    odometry = np.stack([T @ geometry.exp_se3(rng.normal(0.0, sigmas)) for T in rel])
    loop_noise = np.array([np.deg2rad(0.1)] * 3 + [0.05] * 3)
    positions = gt[:, :3, 3]
    loops, last = [], -(10**9)
    for j in range(args.min_gap + 1, len(gt)):
        if j - last < args.every:
            continue
        d = np.linalg.norm(positions[: j - args.min_gap] - positions[j], axis=1)
        i = int(np.argmin(d))
        if d[i] < args.radius:
            loops.append((i, j, geometry.relative(gt[i], gt[j]) @ geometry.exp_se3(rng.normal(0.0, loop_noise))))
            last = j
    return odometry, np.diag(sigmas**2), loops


def drive(backend, odometry: np.ndarray, cov: np.ndarray, loops) -> float:
    from flowslam import geometry

    loop_cov = geometry.pose_covariance(np.deg2rad(1.0), 0.1)
    by_j = {j: (i, j, T) for i, j, T in loops}
    start = time.perf_counter()
    backend.add_odometry(0, None, None)
    for k in range(1, len(odometry) + 1):
        backend.add_odometry(k, odometry[k - 1], cov)
        if k in by_j:
            i, j, T = by_j[k]
            backend.add_loop(i, j, T, loop_cov)
    return time.perf_counter() - start


def parse_overrides(items: list[str]) -> dict:
    import yaml

    out = {}
    for item in items:
        field, _, value = item.partition("=")
        out[field] = yaml.safe_load(value)
    return out


def bench_backend(args: argparse.Namespace) -> bool:
    from flowslam import geometry
    from flowslam.backends.isam2 import Isam2Backend
    from flowslam.config import Isam2Config
    from flowslam.evaluation import ape
    from flowslam.trajectory import read_trajectory

    gt = project_rotations(read_trajectory(args.gt).poses)[: args.frames]
    odometry, cov, loops = make_scenario(gt, args)
    config = Isam2Config(**parse_overrides(args.set))
    print(f"KITTI-00 GT: {len(gt)} poses, {len(loops)} loops at true revisits; noise "
          f"{args.rot_deg} deg / {args.trans_m} m per scan; seed {args.seed}")
    print(f"config: {config.model_dump()}")

    rss0 = peak_rss_mb()
    a_loam = Isam2Backend(config)  # a-loam: the same backend, no loops given
    t_a = drive(a_loam, odometry, cov, [])
    chain_dev = np.abs(a_loam.trajectory() - geometry.compose_relatives(odometry)).max()
    s_loam = Isam2Backend(config)
    t_s = drive(s_loam, odometry, cov, loops)
    t0 = time.perf_counter()
    refined = s_loam.trajectory()
    t_refine = time.perf_counter() - t0
    rss1 = peak_rss_mb()

    def ms(values) -> np.ndarray:
        return np.asarray(values) * 1e3

    upd_a, upd_s = ms(a_loam.update_seconds), ms(s_loam.update_seconds)
    loop_ms = ms([r.seconds for r in s_loam.loops])
    ate = {
        "odometry": ape(s_loam.odometry_trajectory(), gt)["rmse"],
        "isam2 online": ape(s_loam.online_trajectory(), gt)["rmse"],
        "isam2 refined": ape(refined, gt)["rmse"],
    }
    print(f"\na-loam (no loops): total {t_a:.2f} s; update median {np.median(upd_a):.3f} ms, "
          f"p95 {np.percentile(upd_a, 95):.3f} ms, max {upd_a.max():.2f} ms; "
          f"max |a-loam - chained odometry| = {chain_dev:.2e}")
    print(f"s-loam: total {t_s:.2f} s; per-scan update (add_odometry) median {np.median(upd_s):.3f} ms, "
          f"p95 {np.percentile(upd_s, 95):.3f} ms, max {upd_s.max():.2f} ms")
    print(f"  loop updates (factor + {config.extra_iterations_after_loop} extra iteration(s)): "
          f"median {np.median(loop_ms):.1f} ms, max {loop_ms.max():.1f} ms over {len(loop_ms)} loops")
    print(f"  all loop times (ms): {' '.join(f'{x:.0f}' for x in loop_ms)}")
    print(f"  final batch refinement: {t_refine * 1e3:.0f} ms")
    print("  ATE RMSE (m): " + ", ".join(f"{k} {v:.3f}" for k, v in ate.items())
          + f"; refined / odometry = {ate['isam2 refined'] / ate['odometry']:.2f}")
    print(f"  peak RSS: {rss0:.0f} MB before the backends, {rss1:.0f} MB after both runs")
    ok_median = np.median(upd_s) <= MEDIAN_TARGET_MS
    ok_loop = loop_ms.max() <= LOOP_TARGET_MS if len(loop_ms) else True
    print(f"  targets: median <= {MEDIAN_TARGET_MS} ms {'PASS' if ok_median else 'FAIL'}; "
          f"loop updates <= {LOOP_TARGET_MS} ms: median {'PASS' if np.median(loop_ms) <= LOOP_TARGET_MS else 'FAIL'}, "
          f"max {'PASS' if ok_loop else 'FAIL'}")
    return bool(ok_median and ok_loop)


def bench_detector(args: argparse.Namespace) -> None:
    from flowslam import geometry
    from flowslam.datasets import open_dataset
    from flowslam.config import LoopClosureConfig
    from flowslam.loop_closure.detector import ScanContextLoopCloser
    from flowslam.loop_closure.verification import downsample, verify
    from flowslam.trajectory import read_trajectory

    gt = project_rotations(read_trajectory(args.gt).poses)[: args.frames]
    dataset = open_dataset(data_dir() / "kitti-odometry-00-first16")
    scans = [dataset[k].points for k in range(len(dataset))]
    rng = np.random.default_rng(args.seed)
    closer = ScanContextLoopCloser(LoopClosureConfig(distance_threshold=1e-9))
    rss0 = peak_rss_mb()
    for k, pose in enumerate(gt):
        R = geometry.from_euler("z", rng.uniform(0, 2 * np.pi))
        closer.add_scan(k, geometry.transform_points(R, scans[k % len(scans)]), pose @ geometry.inv(R))
    per_scan = np.asarray(closer.stats.seconds_per_scan) * 1e3
    print(f"\nloop closer, {len(gt)} real scans (~124k points each) cycled with random yaw, no verification:")
    print(f"  per scan (descriptor + voxel cloud + storage + search): median {np.median(per_scan):.1f} ms, "
          f"p95 {np.percentile(per_scan, 95):.1f} ms")
    print(f"  held: {closer.memory_bytes() / 2**20:.0f} MB ({closer.memory_bytes() / len(gt) / 1024:.1f} kB/scan); "
          f"peak RSS {rss0:.0f} -> {peak_rss_mb():.0f} MB")

    cfg = LoopClosureConfig().verification
    target = downsample(scans[0], cfg)
    times, accepted = [], 0
    for k in range(1, len(scans)):
        t0 = time.perf_counter()
        result = verify(downsample(scans[k], cfg), target, np.eye(4), cfg)
        times.append((time.perf_counter() - t0) * 1e3)
        accepted += result.accepted
    print(f"  ICP verification (frame 0 vs 1..15, {cfg.voxel_m} m voxels): median {np.median(times):.0f} ms, "
          f"max {np.max(times):.0f} ms; {accepted}/{len(times)} accepted")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.gt.exists():
        print(f"{args.gt}: KITTI-00 GT not found (set FLOWSLAM_DATA)", file=sys.stderr)
        return 2
    ok = bench_backend(args)
    if args.detector:
        bench_detector(args)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
