"""Write a compact copy of a simulated sequence (``flowslam simulate`` output), for carrying
training data to a machine without Open3D (the simulator's ray caster), e.g. a GPU lease
whose transfers are capped (not used by the pipeline or the tests).

Each scan keeps ``--points`` of its points (a seeded random subset, in scan order) with every
per-point ground-truth array; flows and point times are stored in float16 (about 1 mm at
2 m of flow, which the reader widens back to float64), ids in int16. Poses, calibration,
actors and the manifest are copied unchanged, so ``flowslam.datasets.open_dataset`` and
``flowslam train`` read the copy as they read the original.

    python tools/compact_sim.py SRC DST [--points 8192] [--seed 0]
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np

HALF = ("flow", "flow_compensated", "times")
"""Per-point arrays stored in float16."""


def compact(src: Path, dst: Path, points: int, seed: int) -> int:
    """Copy ``src`` to ``dst`` with at most ``points`` points per scan; the number of scans."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.bin", "gt", "preview.png"))
    rng = np.random.default_rng(seed)
    scans = sorted(src.glob("sequences/*/velodyne/*.bin"))
    for scan in scans:
        xyzi = np.fromfile(scan, np.float32).reshape(-1, 4)
        keep = np.arange(len(xyzi))
        if len(keep) > points:
            keep = np.sort(rng.choice(len(keep), points, replace=False))
        out = dst / scan.relative_to(src)
        out.parent.mkdir(parents=True, exist_ok=True)
        xyzi[keep].tofile(out)
        gt = np.load(scan.parent.parent / "gt" / (scan.stem + ".npz"))
        arrays = {}
        for key in gt.files:
            a = gt[key][keep]
            if key in HALF:
                a = a.astype(np.float16)
            elif key == "instance":
                a = a.astype(np.int16)
            arrays[key] = a
        (out.parent.parent / "gt").mkdir(exist_ok=True)
        np.savez_compressed(out.parent.parent / "gt" / (scan.stem + ".npz"), **arrays)
    return len(scans)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--points", type=int, default=8192)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n = compact(args.src, args.dst, args.points, args.seed)
    print(f"{n} scans of at most {args.points} points written to {args.dst}")


if __name__ == "__main__":
    main()
