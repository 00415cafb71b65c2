"""Benchmark of the static refinement (``refine_static_flow``) on replayed real inputs (not a test).

The inputs are recorded once: the ``ssf`` frontend (default configuration, shipped
weights) runs over a sequence -- by default the real KITTI 00 frames 0-15 in
``../shared/data`` -- and every call of ``refine_static_flow`` has its arguments (scan
k-1, flow, static mask, scan k, ``T_init``) saved to ``--inputs`` (an ``.npz``; reused
when it exists). Then the calls are replayed ``--runs`` times and the script reports:

- the median wall time (ms) of the whole call and of each sub-step (the module's helpers
  wrapped with timers: source / target voxel downsampling, dynamic exclusion,
  neighbourhood covariances, planar selection with normals, ICP, fitness, snapping;
  ``other`` = the rest: subsample, the target KD-tree, bookkeeping);
- with ``--old PATH`` (a saved copy of an earlier ``static.py``), the old and the current
  code alternating call by call in this process, their medians, and the largest
  difference between their refined motions (m / deg).

    python tools/bench_static_refinement.py [SEQUENCE] [--runs 5] [--inputs /tmp/static_inputs.npz]
                                             [--old /path/to/old_static.py] [--set FIELD=VALUE ...]

``--set`` gives the current code's calls ``ssf.refine`` options (``FlowRefinementConfig``
fields, e.g. ``--set max_source_points=2000``); the old code keeps its defaults, so
``--old`` on a copy of the current ``static.py`` times an option against the default.

Run with ``OPENBLAS_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE`` like the CLI; the machine's
load average is printed (on a shared machine the timings are upper bounds).
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
ARGS = ("source", "flow", "static_mask", "target", "T_init")
SUB_STEPS = ("_voxel_centroids", "_target_centroids", "_near_any", "_covariances", "_planar_points", "_icp", "_fitness",
             "_snap")


def record(sequence: Path, path: Path) -> list[tuple]:
    """The arguments of every ``refine_static_flow`` call of one ``ssf`` run over ``sequence``."""
    if path.exists():
        z = np.load(path)
        return [tuple(z[f"{name}{i}"] for name in ARGS) for i in range(int(z["n"]))]
    import flowslam.sceneflow.refinement.static as static
    from flowslam.config import SsfConfig
    from flowslam.datasets import open_dataset
    from flowslam.frontends.ssf import SsfFrontend

    calls, original = [], static.refine_static_flow

    def recorder(*args, **kwargs):
        calls.append(tuple(np.array(a) for a in args[:5]))
        return original(*args, **kwargs)

    static.refine_static_flow = recorder
    try:
        frontend, ds = SsfFrontend(SsfConfig()), open_dataset(sequence)
        for i in range(len(ds)):
            frontend.process(ds[i])
    finally:
        static.refine_static_flow = original
    np.savez(path, n=len(calls), **{f"{name}{i}": a for i, call in enumerate(calls) for name, a in zip(ARGS, call)})
    return calls


def load_module(path: Path):
    """A ``static.py`` file as its own module (for old-vs-new comparisons)."""
    spec = importlib.util.spec_from_file_location("static_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look the module up
    spec.loader.exec_module(module)
    return module


def instrument(module, laps: dict[str, list[float]]) -> None:
    """Wrap the module's sub-step helpers so that every call adds its wall time (ms) to ``laps``.

    ``_voxel_centroids`` downsamples the source, ``_target_centroids`` the target;
    ``_planar_points`` includes ``_covariances``."""
    for name in SUB_STEPS:
        fn = getattr(module, name, None)
        if fn is None:
            continue

        @functools.wraps(fn)
        def timed(*args, _fn=fn, _name=name, **kwargs):
            t0 = time.perf_counter()
            out = _fn(*args, **kwargs)
            laps.setdefault(_name, []).append(1e3 * (time.perf_counter() - t0))
            return out

        setattr(module, name, timed)


def per_step_medians(laps: dict[str, list[float]], totals: list[float]) -> dict[str, float]:
    """Median ms per sub-step over the calls, ``other`` = the median of what the steps leave."""
    steps = dict(laps)
    if "_planar_points" in steps and "_covariances" in steps:  # the eigen part alone
        steps["_planar_points"] = [a - b for a, b in zip(steps["_planar_points"], steps["_covariances"])]
    per_call = [sum(v[i] for v in steps.values() if len(v) == len(totals)) for i in range(len(totals))]
    out = {k: statistics.median(v) for k, v in steps.items()}
    out["other"] = statistics.median(t - s for t, s in zip(totals, per_call))
    return out


def pose_difference(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``A^-1 B``."""
    from flowslam import geometry

    E = geometry.inv(A) @ B
    return geometry.translation_norm(E), float(np.degrees(geometry.rotation_angle(E)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", type=Path, default=DATA / "kitti-odometry-00-first16")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--inputs", type=Path, default=Path("/tmp/static_refinement_inputs.npz"),
                    help="recorded inputs (written on the first run, reused later)")
    ap.add_argument("--old", type=Path, default=None, help="an earlier static.py, timed alternating with the current")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="an ssf.refine option for the current code's calls (JSON value)")
    args = ap.parse_args()

    import flowslam.sceneflow.refinement.static as current

    calls = record(args.sequence, args.inputs)
    modules = {"current": current}
    if args.old is not None:
        modules = {"old": load_module(args.old), "current": current}
    options = {name: None for name in modules}
    if args.set:
        from flowslam.config.ssf import FlowRefinementConfig

        pairs = dict(pair.partition("=")[::2] for pair in args.set)
        options["current"] = FlowRefinementConfig(**{k: json.loads(v) for k, v in pairs.items()})
    laps: dict[str, dict[str, list[float]]] = {name: {} for name in modules}
    for name, module in modules.items():
        instrument(module, laps[name])
    totals: dict[str, list[float]] = {name: [] for name in modules}
    worst = (0.0, 0.0)
    for run in range(args.runs):
        for i, call in enumerate(calls):
            order = list(modules) if (run + i) % 2 == 0 else list(modules)[::-1]
            results = {}
            for name in order:
                t0 = time.perf_counter()
                results[name] = modules[name].refine_static_flow(*call, options[name])
                totals[name].append(1e3 * (time.perf_counter() - t0))
            if "old" in results:
                dt, dr = pose_difference(results["old"].T_curr_prev, results["current"].T_curr_prev)
                worst = (max(worst[0], dt), max(worst[1], dr))
    print(f"{args.sequence.name}: {len(calls)} calls x {args.runs} runs; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for name in modules:
        print(f"{name:8s} median {statistics.median(totals[name]):6.1f} ms per call")
        for step, ms in per_step_medians(laps[name], totals[name]).items():
            print(f"    {step:28s} {ms:6.2f} ms")
    if args.old is not None:
        print(f"largest motion difference old vs current: {worst[0]:.2e} m, {worst[1]:.2e} deg")


if __name__ == "__main__":
    main()
