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
        [--weights W] [--from F] [--ab ssf.KEY=VALUE ...]

``--ab ssf.objects.max_iterations=10`` (repeatable; dotted run-config names, YAML values)
runs only an A/B of ``ssf`` options instead: two frontends, the default (A) and one with
the options (B), are fed every frame alternately (which goes first alternates frame by
frame and run by run), so that both share the machine's drift, which on these VMs is
often larger than the effect measured; the report gives each stage's median in both, the
median of the per-frame ratios B/A, and whether the two gave identical outputs (flow,
static mask, motion) on every frame.

``--e2e "ssf.objects.enabled=false ssf.early_network=true"`` (repeatable; dotted run-config
names, YAML values, space-separated) adds an ``ssf`` configuration to the end-to-end runs, in
the same alternation, with its rate against KISS-ICP's: e.g. the odometry-only settings of
the README (``docs/sceneflow_evaluation.md``, stop 76) with ``--skip-stages --from 2``.

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


def _same_output(a, b) -> bool:
    """Whether two ``FrontendOutput`` have identical flow, static mask and motion."""
    return all((x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
               for x, y in ((a.flow, b.flow), (a.static_mask, b.static_mask), (a.T_prev_curr, b.T_prev_curr)))


def run_ab(frames, overrides: dict, network: dict, runs: int, first: int = 1) -> tuple[dict, bool]:
    """``--ab`` (module doc): per frame ``first``.. (>= 1), the ``process`` time and the stage
    times (ms) of the default ``ssf`` (``"A"``) and of one with ``overrides`` (``"B"``, dotted
    run-config names, as :func:`flowslam.config.load_config` takes them), as
    ``{"A": [{stage: ms}, ...], "B": [...]}``; and whether their outputs were identical on
    every frame. Each frontend gets its own copy of the frame."""
    import copy

    from flowslam.config import load_config
    from flowslam.frontends.ssf import SsfFrontend

    base = {f"ssf.network.{k}": v for k, v in network.items()}
    configs = {"A": load_config(frontend="ssf", **base).ssf, "B": load_config(frontend="ssf", **base, **overrides).ssf}
    laps: dict[str, list[dict]] = {"A": [], "B": []}
    same = True
    for run in range(runs):
        frontends = {name: SsfFrontend(config) for name, config in configs.items()}
        for k, frame in enumerate(frames):
            outputs = {}
            for name in ("A", "B") if (k + run) % 2 == 0 else ("B", "A"):
                mine = copy.deepcopy(frame)
                t0 = time.perf_counter()
                outputs[name] = frontends[name].process(mine)
                ms = 1e3 * (time.perf_counter() - t0)
                if k >= first:
                    laps[name].append({"process": ms, **outputs[name].stats.get("stage_ms", {})})
            same &= _same_output(outputs["A"], outputs["B"])
    return laps, same


def print_ab(laps: dict, same: bool, overrides: dict) -> None:
    """The report of :func:`run_ab`."""
    print("A: default ssf; B: " + ", ".join(f"{k}={v}" for k, v in overrides.items()))
    for stage in laps["A"][0]:
        pairs = [(a[stage], b[stage]) for a, b in zip(laps["A"], laps["B"]) if stage in a and stage in b]
        ratios = [b / a for a, b in pairs if a > 0]
        a_ms, b_ms = statistics.median(p[0] for p in pairs), statistics.median(p[1] for p in pairs)
        ratio = f"{statistics.median(ratios):.3f}" if ratios else "-"
        print(f"{stage:>13}: A {a_ms:7.1f} ms, B {b_ms:7.1f} ms (medians of {len(pairs)} frames); "
              f"median per-frame B/A {ratio}")
    print(f"outputs identical on every frame: {'yes' if same else 'no'}")


END_TO_END = {
    "ssf lookahead": ("ssf", {}),
    "ssf sequential": ("ssf", {"ssf": {"lookahead": False}}),
    "kiss-icp": ("kiss-icp", {}),
}


def dotted_options(items: list[str]) -> dict:
    """``["ssf.a.b=1", "ssf.c=x"]`` as ``{"ssf.a.b": 1, "ssf.c": "x"}`` (dotted run-config names,
    YAML values): ``--ab``'s and ``--e2e``'s options."""
    import yaml

    return {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in items)}


def nested_options(text: str) -> dict:
    """``--e2e``'s ``"ssf.a.b=1 ssf.c=x"`` as the nested mapping ``PipelineConfig`` takes:
    ``{"ssf": {"a": {"b": 1}, "c": "x"}}`` (a null value keeps the default, as with ``--ab``)."""
    from flowslam.config import set_dotted

    nested: dict = {}
    set_dotted(nested, dotted_options(text.split()))
    return nested


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
    ap.add_argument("--e2e", action="append", default=[], metavar="'KEY=VALUE ...'",
                    help="also this ssf configuration end to end (dotted options, space-separated)")
    ap.add_argument("--ab", action="append", default=[], metavar="KEY=VALUE",
                    help="only an A/B: the default ssf against ssf with these options (dotted, e.g. "
                         "ssf.objects.max_iterations=10), frame by frame")
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
    if args.ab:
        overrides = dotted_options(args.ab)
        print_ab(*run_ab(frames, overrides, network, args.runs, first), overrides)
        print(f"load average after: {os.getloadavg()[0]:.2f}")
        return
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
    runs = {**END_TO_END, **{f"ssf {text}": ("ssf", nested_options(text)) for text in args.e2e}}
    rates: dict[str, list[float]] = {name: [] for name in runs}
    laps: dict[str, list[float]] = {name: [] for name in runs}
    waits: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[tuple[float, float]]] = {name: [] for name in runs}
    for _ in range(args.runs):  # alternating, so that the configurations share the load
        for name, (frontend, options) in runs.items():
            rate, seconds, waited, cpu_ms = run_end_to_end(args.sequence, args.frames, frontend, options, network,
                                                           first)
            rates[name].append(rate)
            laps[name] += seconds
            waits[name] += waited
            cpu[name].append((cpu_ms, cpu_ms * rate / 1e3))  # CPU per frame, cores busy
    for name in runs:
        rate = statistics.median(rates[name])
        wait = f"; waited for the background {statistics.median(waits[name]):.0f} ms" if waits[name] else ""
        cpu_ms, cores = (statistics.median(column) for column in zip(*cpu[name]))
        print(f"{'end to end ' + name:>28}: {rate:5.2f} frames/s (median of {args.runs} runs; per frame "
              f"median {1e3 * statistics.median(laps[name]):.0f} ms{wait}; CPU {cpu_ms:.0f} ms per frame, "
              f"{cores:.2f} cores busy), -b isam2 defaults")
    for name in ["ssf lookahead", *(f"ssf {text}" for text in args.e2e)]:
        ratio = statistics.median(rates[name]) / statistics.median(rates["kiss-icp"])
        print(f"{name} / kiss-icp rate: {ratio:.2f}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
