"""Benchmark of the ``ssf`` network stage on each torch device this machine has (not a test).

Runs ``NetworkStage`` (shipped weights; sampling, forward pass, propagation to every point
of scan k-1) over consecutive pairs of a KITTI-format sequence -- by default the real KITTI
00 frames in ``../shared/data`` -- once per configuration, in the same process:

- ``cpu``: the CPU path the frontend takes (BatchNorms folded, ``--threads`` torch threads);
- ``cuda fp32`` and ``cuda bf16`` (``ssf.network.cuda_bf16``), when torch sees a GPU;
- with ``--grid-half-extent M``, also ``cpu crop M`` and ``cuda fp32 crop M``: the network on the
  +-M m square (``ssf.network.grid_half_extent_m``), the GPU one compared with the CPU crop.

The history poses are the sequence's GT poses (they stand in for the frontend's own
poses; the timing does not depend on them). For each configuration: median and minimum
wall time per pair over ``--runs`` passes, the time of the CPU-side input sampling alone, (the first pass also warms the device up and is
not counted when ``--runs`` > 1), and, against the CPU's output on the same pairs, the
largest and the median flow difference (m) and the share of points whose static/dynamic
call agrees.

    python tools/bench_network_device.py [SEQUENCE] [--frames 8] [--runs 5] [--threads 1]
        [--grid-half-extent 38.4] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def configurations(crop_m: float | None = None) -> dict[str, dict]:
    """Network options per configuration name, the GPU ones only when CUDA is present; with
    ``crop_m``, the CPU and fp32 GPU configurations again on the +-``crop_m`` m square."""
    import torch

    cuda = torch.cuda.is_available()
    configs = {"cpu": {"device": "cpu"}}
    if cuda:
        configs["cuda fp32"] = {"device": "cuda"}
        configs["cuda bf16"] = {"device": "cuda", "cuda_bf16": True}
    if crop_m is not None:
        configs[f"cpu crop {crop_m:g}"] = {"device": "cpu", "grid_half_extent_m": crop_m}
        if cuda:
            configs[f"cuda fp32 crop {crop_m:g}"] = {"device": "cuda", "grid_half_extent_m": crop_m}
    return configs


def run_pairs(frames, options: dict, threads: int, runs: int):
    """Per-pass lists of per-pair wall times (ms), the last pass's (flow, static) per pair, and
    the median time (ms) of the CPU-side input sampling (``NetworkStage._sample``) alone."""
    from flowslam.config import SsfConfig
    from flowslam.frontends.ssf_stages import NetworkStage, PairState

    stage = NetworkStage(SsfConfig(network={**options, "num_threads": threads}))
    T = stage.num_frames
    poses = [f.gt_pose for f in frames]
    passes, outputs, sampling = [], [], []
    for _ in range(runs):
        times, outputs = [], []
        for k in range(1, len(frames)):
            lo = max(0, k - (T - 1))
            state = PairState(prev=frames[k - 1], frame=frames[k], history=frames[lo:k],
                              history_poses=poses[lo:k], T_world_guess=poses[k])
            if not passes:  # first pass: the CPU-side input sampling alone, once per pair
                t0 = time.perf_counter()
                stage._sample(state)
                sampling.append(1e3 * (time.perf_counter() - t0))
            t0 = time.perf_counter()
            stage.run(state)
            times.append(1e3 * (time.perf_counter() - t0))
            outputs.append((state.flow, state.static))
        passes.append(times)
    return passes, outputs, statistics.median(sampling)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", type=Path, default=DATA / "kitti-odometry-00-first16")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the CPU configuration")
    ap.add_argument("--grid-half-extent", type=float, help="also time the network on this square (m)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()

    import torch

    from flowslam.datasets import open_dataset

    ds = open_dataset(args.sequence)
    frames = [ds[i] for i in range(min(args.frames, len(ds)))]
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "none"
    print(f"{args.sequence}: {len(frames) - 1} pairs, ~{np.mean([len(f.points) for f in frames]):.0f} points/scan; "
          f"torch {torch.__version__}, GPU: {gpu}, CPU cores: {os.cpu_count()}, load {os.getloadavg()[0]:.2f}")
    results, references = {}, {}
    for name, options in configurations(args.grid_half_extent).items():
        passes, outputs, sampling_ms = run_pairs(frames, options, args.threads, args.runs)
        counted = [t for p in (passes[1:] or passes) for t in p]
        row = {"median_ms": statistics.median(counted), "min_ms": min(counted), "pairs": len(counted),
               "sampling_ms": sampling_ms}
        crop = options.get("grid_half_extent_m")  # each configuration is compared with the CPU on its grid
        reference = references.setdefault(crop, outputs)
        if reference is not outputs:
            diff = np.concatenate([np.linalg.norm(f - rf, axis=1) for (f, _), (rf, _) in zip(outputs, reference)])
            agree = np.concatenate([s == rs for (_, s), (_, rs) in zip(outputs, reference)])
            row.update(max_flow_diff_m=float(diff.max()), median_flow_diff_m=float(np.median(diff)),
                       static_agreement=float(agree.mean()))
        results[name] = row
        extra = "" if "max_flow_diff_m" not in row else (
            f"  vs its cpu: flow diff max {row['max_flow_diff_m']:.2e} m, median {row['median_flow_diff_m']:.2e} m, "
            f"static/dynamic agree {100 * row['static_agreement']:.3f} %")
        print(f"{name:>19}: median {row['median_ms']:7.1f} ms, min {row['min_ms']:7.1f} ms per pair "
              f"(input sampling alone {sampling_ms:.1f} ms){extra}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"gpu": gpu, "torch": torch.__version__, "results": results}, indent=2))


if __name__ == "__main__":
    main()
