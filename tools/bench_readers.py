#!/usr/bin/env python
"""Reader throughput benchmark: frames/s and Mpoints/s (median of several passes).

Readers: the real KITTI extract, folders of .npy / binary .pcd / ASCII .pcd scans and a
ROS2 mcap bag (all written to a temp dir from the KITTI scans), and the real AV2 log.
Each pass reads every frame through ``Dataset.__getitem__`` (random access, includes
sanitising); for the bag, streaming iteration is measured too. Opening (indexing) is
timed separately. Not a test: run ``python tools/bench_readers.py [--passes 5]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam.datasets import Dataset, open_dataset

REPO = Path(__file__).resolve().parents[1]
KITTI = "kitti-odometry-00-first16"
AV2 = "argoverse2-sensor-val-pair/val/7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def default_data_dir() -> Path:
    env = os.environ.get("FLOWSLAM_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def write_npy_folder(ds: Dataset, out: Path) -> Path:
    out.mkdir()
    for f in ds:
        np.save(out / f"{f.index:06d}.npy", np.column_stack([f.points, f.intensity]).astype(np.float32))
    return out


def write_pcd_folder(ds: Dataset, out: Path, ascii_: bool) -> Path:
    import open3d as o3d

    out.mkdir()
    for f in ds:
        pc = o3d.t.geometry.PointCloud()
        pc.point.positions = o3d.core.Tensor(f.points.astype(np.float32))
        pc.point.intensity = o3d.core.Tensor(f.intensity.astype(np.float32).reshape(-1, 1))
        o3d.t.io.write_point_cloud(str(out / f"{f.index:06d}.pcd"), pc, write_ascii=ascii_)
    return out


def write_mcap_bag(ds: Dataset, out: Path) -> Path:
    from flowslam.datasets.rosbag_writer import BagMessage, make_pointcloud2, typestore_for, write_bag

    ts = typestore_for("mcap")
    layout = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("t", "u4")]
    msgs = []
    for f in ds:
        stamp = 1_700_000_000_000_000_000 + f.index * 100_000_000
        cols = {"x": f.points[:, 0], "y": f.points[:, 1], "z": f.points[:, 2], "intensity": f.intensity,
                "t": np.zeros(len(f), np.uint32)}
        msgs.append(BagMessage("/points", "sensor_msgs/msg/PointCloud2", stamp, make_pointcloud2(ts, stamp, cols, layout)))
    return write_bag(out, "mcap", msgs)


def time_passes(read_all: Callable[[], int], passes: int) -> tuple[float, int]:
    """Median seconds of ``passes`` calls of ``read_all`` (returns total points read), and the points."""
    times, points = [], 0
    for _ in range(passes):
        t0 = time.perf_counter()
        points = read_all()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), points


def random_access(ds: Dataset) -> Callable[[], int]:
    return lambda: sum(len(ds[i]) for i in range(len(ds)))


def streaming(ds: Dataset) -> Callable[[], int]:
    return lambda: sum(len(f) for f in ds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_data_dir(), help="the shared data folder")
    ap.add_argument("--passes", type=int, default=5, help="passes per reader (median reported)")
    args = ap.parse_args()

    kitti_path, av2_path = args.data / KITTI, args.data / AV2
    if not kitti_path.exists():
        raise SystemExit(f"{kitti_path}: does not exist (set --data or FLOWSLAM_DATA)")
    rows: list[tuple[str, float, int, float, int]] = []

    def bench(label: str, path: Path, mode: str = "random") -> None:
        t0 = time.perf_counter()
        ds = open_dataset(path)
        t_open = time.perf_counter() - t0
        fn = streaming(ds) if mode == "stream" else random_access(ds)
        fn()  # warm-up (page cache, imports)
        sec, points = time_passes(fn, args.passes)
        rows.append((label, t_open, len(ds), sec, points))
        if hasattr(ds, "close"):
            ds.close()

    with tempfile.TemporaryDirectory(prefix="flowslam_bench_") as tmp:
        tmp_path = Path(tmp)
        kitti = open_dataset(kitti_path)
        bench("kitti .bin (real extract)", kitti_path)
        bench("folder .npy float32", write_npy_folder(kitti, tmp_path / "npy"))
        bench("folder .pcd binary", write_pcd_folder(kitti, tmp_path / "pcd_bin", ascii_=False))
        bench("folder .pcd ascii", write_pcd_folder(kitti, tmp_path / "pcd_ascii", ascii_=True))
        bag = write_mcap_bag(kitti, tmp_path / "bag_mcap")
        bench("rosbag2 mcap, random access", bag)
        bench("rosbag2 mcap, streaming", bag, mode="stream")
        if av2_path.exists():
            bench("argoverse2 .feather (+flow)", av2_path)

    print(f"reader throughput, median of {args.passes} passes (every frame read + sanitised)\n")
    head = f"{'reader':32s} {'open ms':>8s} {'frames':>6s} {'ms/frame':>9s} {'frames/s':>9s} {'Mpts/s':>7s}"
    print(head)
    print("-" * len(head))
    for label, t_open, n, sec, points in rows:
        print(f"{label:32s} {t_open * 1e3:8.1f} {n:6d} {sec / n * 1e3:9.2f} {n / sec:9.1f} {points / sec / 1e6:7.2f}")


if __name__ == "__main__":
    main()
