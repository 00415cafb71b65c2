"""Benchmark of the whole ``ssf`` frontend per frame, stage by stage (not a test).

Runs ``SsfFrontend`` (shipped weights, BatchNorms folded) over a sequence -- by default
the real KITTI 00 frames 0-15 in ``../shared/data`` -- ``--runs`` times, and reports the
median wall time per frame of each stage (``FrontendOutput.stats["stage_ms"]``: network
forward + propagation, pose start, static refinement, flow-to-pose, objects)
and of the whole ``process`` call, plus the frame rate it allows. Three configurations
run in the same process, one after the other, so that they share the machine's load:

- ``network only``: ``refine.enabled: false`` (flow-to-pose on the network's flow);
- ``refine``: static refinement, no objects;
- ``full`` (the default configuration): refinement and objects.

Stage times come from ``process`` calls one after the other, without the run loop's
read-ahead, so the network never runs ahead there. Then the **end-to-end** rate of the
run loop as ``flowslam run -f F -b isam2`` drives it (read + frontend + iSAM2 backend +
loop closing + mapping + output sinks, no files written), ``--runs`` times each,
alternating: ``ssf`` with the next pair's network and static refinement in a background
thread (``ssf.lookahead``, the default), ``ssf`` in one thread, and ``kiss-icp`` (the rate
the issue compares against). A rate is frames after the first / wall time of the loop;
the median per-frame time is printed beside it, and the CPU time the whole process (every
thread) spent per frame with the cores it kept busy on average (CPU time / wall time): with
``ssf.lookahead`` on two cores, a rate far below 2 / (CPU per frame) says the threads wait
for each other; a rate near it says only less work per frame makes it faster.

    python tools/bench_ssf_pipeline.py [SEQUENCE] [--runs 3] [--threads N] [--frames 16] [--skip-stages]
        [--weights W] [--from F]

``--weights`` runs every ``ssf`` configuration with those network weights (e.g. from
``flowslam adapt``) instead of the shipped ones. ``--from F`` still runs every frame but
counts only frames F.. in the medians and rates, e.g. the frames held out of an
adaptation on the sequence's first ones.

The machine's load average is printed: on a shared machine the timings are upper bounds.
The thread-pool environment is the one ``flowslam run`` sets (``flowslam.threads``:
passive OpenMP waiting, one OpenBLAS thread; a variable set by the user wins) and is
printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

from flowslam.threads import set_thread_defaults

THREAD_ENV = set_thread_defaults()  # as `flowslam run` does, before numpy loads

import numpy as np  # noqa: E402

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

CONFIGS = {
    "network only": {"refine": {"enabled": False}},
    "refine": {"objects": {"enabled": False}},
    "full": {},
}


def network_options(threads: int | None, weights: Path | None) -> dict:
    """``ssf.network`` options of every ``ssf`` configuration: torch threads, and the
    weights when not the shipped ones."""
    return {"num_threads": threads, **({"weights": weights} if weights else {})}


def run_once(frames, options: dict, network: dict, first: int = 1) -> tuple[list[float], dict[str, list[float]]]:
    """Per-frame wall times (ms) of ``process`` and of each stage, frames ``first``.. (>= 1)
    of one pass over ``frames``."""
    from flowslam.config import SsfConfig
    from flowslam.frontends.ssf import SsfFrontend

    frontend = SsfFrontend(SsfConfig(network=network, **options))
    totals, stages = [], {}
    for k, frame in enumerate(frames):
        t0 = time.perf_counter()
        out = frontend.process(frame)
        if k < first:
            continue
        totals.append(1e3 * (time.perf_counter() - t0))
        for name, ms in out.stats.get("stage_ms", {}).items():
            stages.setdefault(name, []).append(ms)
    return totals, stages


END_TO_END = {
    "ssf lookahead": ("ssf", {}),
    "ssf sequential": ("ssf", {"ssf": {"lookahead": False}}),
    "kiss-icp": ("kiss-icp", {}),
}


def run_end_to_end(sequence: Path, n_frames: int, frontend: str, options: dict, network: dict, first: int = 1):
    """(frames/s from frame ``first`` (>= 1) on, per-frame seconds, per-frame ms the
    frontend waited for the stages run ahead (empty without them), CPU ms per frame of the
    whole process (every thread) over the same frames) of the run loop on ``sequence``'s
    first ``n_frames``; every frame runs, only frames ``first``.. count."""
    from flowslam.config import PipelineConfig
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import drive
    from flowslam.slam import Slam

    if frontend == "ssf":
        options = {**options, "ssf": {**options.get("ssf", {})}}
        options["ssf"]["network"] = {**options["ssf"].get("network", {}), **network}
    config = PipelineConfig(frontend=frontend, backend="isam2", **options)
    dataset = open_dataset(sequence, config.dataset)
    slam = Slam(config)
    laps = []
    result = drive(slam, dataset, range(min(n_frames, len(dataset))),
                   on_frame=lambda k, seconds: laps.append((time.perf_counter(), time.process_time(), seconds)))
    if result.error is not None:
        raise result.error
    counted = len(laps) - first
    wall = laps[-1][0] - laps[first - 1][0]  # from the end of frame first-1 to the end of the last
    cpu_ms = 1e3 * (laps[-1][1] - laps[first - 1][1]) / counted
    waits = [stats["ahead_wait_ms"] for stats in result.frontend_stats[first:] if "ahead_wait_ms" in stats]
    return counted / wall, [seconds for _, _, seconds in laps[first:]], waits, cpu_ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", type=Path, default=DATA / "kitti-odometry-00-first16")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None,
                    help="torch threads of the network (default: the frontend's own default)")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--weights", type=Path, default=None, help="network weights of ssf (default: shipped)")
    ap.add_argument("--from", dest="first", type=int, default=1, help="count frames from this one on (all run)")
    ap.add_argument("--skip-stages", action="store_true", help="only the end-to-end rates")
    args = ap.parse_args()

    from flowslam.datasets import open_dataset

    ds = open_dataset(args.sequence)
    frames = [ds[i] for i in range(min(args.frames, len(ds)))]
    n_points = int(np.median([len(f.points) for f in frames]))
    network = network_options(args.threads, args.weights)
    first = max(args.first, 1)  # frame 0 has no pair
    print(f"{args.sequence.name}: {len(frames)} frames (counted from {first}), median {n_points} points; "
          f"weights {args.weights or 'shipped'}; threads {args.threads or 'default'}; "
          f"load average {os.getloadavg()[0]:.2f}; " + " ".join(f"{k}={v}" for k, v in THREAD_ENV.items()))
    for name, options in ({} if args.skip_stages else CONFIGS).items():
        totals, stages = [], {}
        for _ in range(args.runs):
            t, s = run_once(frames, options, network, first)
            totals += t
            for k, v in s.items():
                stages.setdefault(k, []).extend(v)
        median = statistics.median(totals)
        parts = ", ".join(f"{k} {statistics.median(v):.0f}" for k, v in stages.items())
        print(f"{name:>13}: {median:6.0f} ms/frame ({1e3 / median:4.1f} Hz) median of {len(totals)}; "
              f"stages (median ms): {parts}")
    rates: dict[str, list[float]] = {name: [] for name in END_TO_END}
    laps: dict[str, list[float]] = {name: [] for name in END_TO_END}
    waits: dict[str, list[float]] = {name: [] for name in END_TO_END}
    cpu: dict[str, list[tuple[float, float]]] = {name: [] for name in END_TO_END}
    for _ in range(args.runs):  # alternating, so that the configurations share the load
        for name, (frontend, options) in END_TO_END.items():
            rate, seconds, waited, cpu_ms = run_end_to_end(args.sequence, args.frames, frontend, options, network,
                                                           first)
            rates[name].append(rate)
            laps[name] += seconds
            waits[name] += waited
            cpu[name].append((cpu_ms, cpu_ms * rate / 1e3))  # CPU per frame, cores busy
    for name in END_TO_END:
        rate = statistics.median(rates[name])
        wait = f"; waited for the background {statistics.median(waits[name]):.0f} ms" if waits[name] else ""
        cpu_ms, cores = (statistics.median(column) for column in zip(*cpu[name]))
        print(f"{'end to end ' + name:>28}: {rate:5.2f} frames/s (median of {args.runs} runs; per frame "
              f"median {1e3 * statistics.median(laps[name]):.0f} ms{wait}; CPU {cpu_ms:.0f} ms per frame, "
              f"{cores:.2f} cores busy), -b isam2 defaults")
    ratio = statistics.median(rates["ssf lookahead"]) / statistics.median(rates["kiss-icp"])
    print(f"ssf (lookahead) / kiss-icp rate: {ratio:.2f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
