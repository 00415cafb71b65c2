"""Benchmark of the scene-flow network on CPU (not a test).

Real KITTI 00 scans (``../shared/data/kitti-odometry-00-first16``, HDL-64E, ~121k points):
frames 0-4, the four older ones moved into frame 4 with the GT poses (standing in for
the system's own ego-motion), each randomly sub-sampled to 16k / 32k points; the
network predicts flow for the sampled points of frame 3 and ``propagate`` spreads it to
all ~120k points of frame 3. Timed end to end per new frame as a streaming frontend
would run (sub-sample the newest scan, gather the five samples, forward, propagate;
older scans keep the sample drawn when they arrived), BatchNorms folded, untrained
weights (timing does not depend on them): median and minimum wall time of ``--runs``
and the median process CPU time (with one thread: the time on a dedicated core).
Also: where the time of one frame goes (``--parts``: pillar indexing, PointNet pooling, stem +
U-Net, decoder inputs, FlowSSM decoder, propagation; medians of ``--runs``), chunked vs.
sequential selective scan, and parameters / size of each preset.

    python tools/bench_sceneflow.py [--threads 2] [--runs 9] [--preset tiny] [--parts] [--no-tune-allocator]

The machine's load average is printed: on a shared machine the timings are upper bounds.
With two threads on a *loaded* machine, OpenMP's spinning threads wait a scheduler slice
(~7 ms) at every parallel op and a forward pass can take seconds: run with
``OMP_WAIT_POLICY=PASSIVE`` (or ``--threads 1``) there; under PASSIVE the ``ssf`` frontend
uses one thread by default (``default_cpu_threads``). The glibc allocator is tuned
(``tune_cpu_allocator``) unless ``--no-tune-allocator``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from flowslam import geometry
from flowslam.sceneflow.network.model import ModelConfig, SceneFlowNet, tune_cpu_allocator
from flowslam.sceneflow.network.propagate import propagate, random_subsample
from flowslam.sceneflow.network import selective_scan as selective_scan_module
from flowslam.sceneflow.network.selective_scan import selective_scan, selective_scan_reference

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def _timeit(fn, runs: int) -> tuple[float, float, float]:
    """Median and minimum wall time and median process CPU time of ``fn``, in ms.

    With one thread the CPU time is what a dedicated core would take (wall time also
    counts time the scheduler gave to other processes).
    """
    fn()  # warm-up
    ts, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * statistics.median(ts), 1e3 * min(ts), 1e3 * statistics.median(cpu)


def load_kitti(num_frames: int) -> list[np.ndarray]:
    """The first ``num_frames`` scans, all in the sensor frame of the newest (GT poses)."""
    from flowslam.datasets import open_dataset

    ds = open_dataset(DATA / "kitti-odometry-00-first16")
    frames = [ds[i] for i in range(num_frames)]
    T_w_new = frames[-1].gt_pose
    return [geometry.transform_points(geometry.inv(T_w_new) @ f.gt_pose, f.points) for f in frames]


def bench_model(preset: str, frames: list[np.ndarray], samples: int, runs: int) -> dict:
    net = SceneFlowNet(ModelConfig.preset(preset, num_frames=len(frames))).fold_batchnorm()
    gen = torch.Generator().manual_seed(0)
    full = [torch.from_numpy(f.astype(np.float32)) for f in frames]
    src = len(frames) - 2
    state = {}

    # streaming: the older frames were sub-sampled when they arrived; only the newest is new
    idx = [random_subsample(len(f), samples, gen) for f in full]

    def pipeline():
        with torch.inference_mode():
            idx[-1] = random_subsample(len(full[-1]), samples, gen)
            out = net({"points": [[f[i] for f, i in zip(full, idx)]]})
            values = torch.cat([out["flow"], out["dynamic_logit"].unsqueeze(1)], 1)
            state["all"] = propagate(full[src], idx[src], values)

    def forward_only():
        with torch.inference_mode():
            net({"points": [[f[:samples] for f in full]]})

    med, best, cpu = _timeit(pipeline, runs)
    fmed, fbest, fcpu = _timeit(forward_only, runs)
    return {
        "points_per_frame": samples,
        "flow_rows": int(state["all"].shape[0]),
        "pipeline_median_ms": med,
        "pipeline_min_ms": best,
        "pipeline_cpu_ms": cpu,
        "forward_median_ms": fmed,
        "forward_min_ms": fbest,
        "forward_cpu_ms": fcpu,
    }


def bench_parts(preset: str, frames: list[np.ndarray], samples: int, runs: int) -> dict[str, float]:
    """Median wall time (ms) of each part of one frame at ``samples`` points per frame (the
    pillar stage and stem as the model runs them: compiled on the occupied pillars)."""
    from flowslam.sceneflow.network.compiled_pillars import pillars_and_stem
    from flowslam.sceneflow.network.voxelize import index_points

    net = SceneFlowNet(ModelConfig.preset(preset, num_frames=len(frames))).fold_batchnorm()
    gen = torch.Generator().manual_seed(0)
    full = [torch.from_numpy(f.astype(np.float32)) for f in frames]
    idx = [random_subsample(len(f), samples, gen) for f in full]
    points = [[f[i] for f, i in zip(full, idx)]]
    src = len(frames) - 2
    with torch.inference_mode():
        index, _ = index_points(points, net.grid)
        pillars = pillars_and_stem(net.pillars, net.stem, index)
        feats = net.backbone(pillars.stem)
        sel = torch.nonzero(index.time == src).squeeze(1)
        lookup = (pillars.table, pillars.row_of, feats, pillars.point_feats, pillars.raw)
        inputs = net._source_inputs(index, sel, *lookup)
        out = net(points)
        values = torch.cat([out["flow"], out["dynamic_logit"].unsqueeze(1)], 1)
        parts = {
            "pillar index": lambda: index_points(points, net.grid),
            "PointNet + pooling + stem": lambda: pillars_and_stem(net.pillars, net.stem, index),
            "U-Net": lambda: net.backbone(pillars.stem),
            "decoder inputs": lambda: net._source_inputs(index, sel, *lookup),
            "FlowSSM decoder": lambda: net.decoder(*inputs[:2], index.batch[sel], inputs[2], index.batch_size),
            "propagation": lambda: propagate(full[src], idx[src], values),
        }
        return {name: _timeit(fn, runs)[0] for name, fn in parts.items()}


def bench_scan(runs: int) -> list[str]:
    lines = []
    g = torch.Generator().manual_seed(0)
    for L, Dm, S in ((4096, 16, 8), (16384, 32, 8), (32768, 32, 8)):
        x = torch.randn(1, L, Dm, generator=g)
        delta = torch.nn.functional.softplus(torch.randn(1, L, Dm, generator=g)) * 0.1
        A = -torch.rand(Dm, S, generator=g)
        B, C = torch.randn(1, L, S, generator=g), torch.randn(1, L, S, generator=g)
        D = torch.randn(Dm, generator=g)
        with torch.no_grad():
            selective_scan_module.COMPILED_INFERENCE = False
            try:
                med, best, _ = _timeit(lambda: selective_scan(x, delta, A, B, C, D, chunk=128), runs)
            finally:
                selective_scan_module.COMPILED_INFERENCE = True
            cmed, _, _ = _timeit(lambda: selective_scan(x, delta, A, B, C, D, chunk=128), runs)
        line = f"  L={L:6d} Dm={Dm} S={S}: chunked {med:7.1f} ms (min {best:.1f}), compiled (inference) {cmed:6.1f} ms"
        if L <= 4096:
            with torch.no_grad():
                rmed, _, _ = _timeit(lambda: selective_scan_reference(x, delta, A, B, C, D), 1)
            line += f", sequential loop {rmed:7.1f} ms ({rmed / med:.0f}x slower)"
        ins = [t.clone().requires_grad_() for t in (x, delta, A, B, C, D)]
        bmed, _, _ = _timeit(lambda: selective_scan(*ins, chunk=128).sum().backward(), max(3, runs // 3))
        lines.append(line + f"; forward+backward {bmed:.1f} ms")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=9)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--parts", action="store_true", help="also time each part of a frame (16,384 points/frame)")
    ap.add_argument("--no-tune-allocator", action="store_true", help="keep glibc's default malloc thresholds")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    tuned = False if args.no_tune_allocator else tune_cpu_allocator()
    print(f"torch {torch.__version__}, {args.threads} thread(s), allocator tuned: {tuned}, "
          f"load average {os.getloadavg()}")

    print("presets (parameters, size as in MambaFlow Table V):")
    for name in ("tiny", "full"):
        net = SceneFlowNet(ModelConfig.preset(name))
        cfg = net.config
        print(f"  {name:5s} {net.count_parameters() / 1e6:6.3f} M params, {net.size_mb():6.2f} MB "
              f"(voxel {cfg.voxel_size} m, grid {cfg.grid.size}^2, U-Net stride {cfg.stem_stride}, "
              f"widths {cfg.widths})")

    frames = load_kitti(args.frames)
    print(f"KITTI 00 frames 0-{args.frames - 1}: {[len(f) for f in frames]} points; "
          f"flow for all {len(frames[-2])} points of frame {args.frames - 2}")
    for n in (16384, 32768):
        r = bench_model(args.preset, frames, n, args.runs)
        print(f"  {args.preset} @ {n} pts/frame: end-to-end wall median {r['pipeline_median_ms']:.1f} ms "
              f"(min {r['pipeline_min_ms']:.1f}, CPU {r['pipeline_cpu_ms']:.1f}); forward only median "
              f"{r['forward_median_ms']:.1f} ms (min {r['forward_min_ms']:.1f}, CPU {r['forward_cpu_ms']:.1f}); "
              f"{r['flow_rows']} flow rows")

    if args.parts:
        parts = bench_parts(args.preset, frames, 16384, args.runs)
        print("  parts of one frame @ 16384 pts/frame (median ms): "
              + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()))

    print("selective scan, chunk 128:")
    for line in bench_scan(args.runs):
        print(line)
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
