"""Benchmark of the LiDAR simulator (not a test): frames/s per sensor, dynamic points per preset.

    python tools/bench_simulator.py                 # everything (a few minutes on 2 cores)
    python tools/bench_simulator.py --part speed    # frames/s only
    python tools/bench_simulator.py --part presets --frames 300

Speed, per sensor, with and without motion distortion: ray casting + ground truth of one
frame in this process (``render``), on the ``dt`` scene. ``end-to-end`` runs
``simulate()`` (scene building, rendering in worker processes, writing the files) and
divides the frames by the rendering-and-writing time. Dynamic points: mean / min / max
per frame and the share of dynamic points over a sequence of each preset (64 x 2048).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np


def _scene(preset: str, frames: int, seed: int, sensor):
    from flowslam.simulation.presets import get_preset
    from flowslam.simulation.simulator import build_scene

    return build_scene(get_preset(preset), frames, seed, sensor)


def bench_speed(frames: int, seed: int) -> list[dict]:
    from flowslam.simulation.ground_truth import make_frame
    from flowslam.simulation.raycast import Raycaster
    from flowslam.simulation.sensors import SENSORS, get_sensor

    rows = []
    for name in SENSORS:
        sensor = get_sensor(name)
        _, ego, world, actors = _scene("dt", frames, seed, sensor)
        caster = Raycaster(world, actors, sensor)
        for distortion in (False, True):
            caster.cast(0.0, ego.sensor, distortion)  # warm-up
            t_cast = t_gt = 0.0
            points = 0
            for k in range(frames):
                t0, t1 = float(ego.frame_times[k]), float(ego.frame_times[k + 1])
                a = time.perf_counter()
                raw = caster.cast(t0, ego.sensor, distortion)
                b = time.perf_counter()
                f = make_frame(raw, caster, ego.sensor, t0, t1, distortion, np.random.default_rng(k))
                c = time.perf_counter()
                t_cast += b - a
                t_gt += c - b
                points += len(f.points)
            rows.append({
                "sensor": name, "rays": sensor.rays_per_sweep, "distortion": distortion,
                "points": points / frames, "cast_ms": 1e3 * t_cast / frames, "gt_ms": 1e3 * t_gt / frames,
                "render_fps": frames / (t_cast + t_gt),
            })
            print(f"{name:8s} {sensor.beams:3d}x{sensor.columns:<5d} distortion={'on ' if distortion else 'off'} "
                  f"{points / frames:8.0f} points  cast {1e3 * t_cast / frames:6.1f} ms  gt {1e3 * t_gt / frames:5.1f} ms"
                  f"  render {frames / (t_cast + t_gt):5.1f} frames/s", flush=True)
    return rows


def bench_end_to_end(frames: int, seed: int) -> list[dict]:
    from flowslam.simulation.simulator import simulate

    rows = []
    for sensor, distortion in (("hdl64", False), ("hdl64", True), ("vlp16", False)):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            m = simulate(tmp, preset="dt", frames=frames, seed=seed, sensor=sensor, distortion=distortion)
            total = time.perf_counter() - t
        row = {"sensor": sensor, "distortion": distortion, "frames": frames, **m["timing_s"], "total_s": total}
        rows.append(row)
        print(f"simulate(dt, {sensor}, distortion={'on' if distortion else 'off'}, {frames} frames): scene "
              f"{m['timing_s']['scene']:.1f} s, render+write {m['timing_s']['render_and_write']:.1f} s = "
              f"{m['timing_s']['frames_per_s']:.1f} frames/s, total {total:.1f} s", flush=True)
    return rows


def bench_presets(frames: int, seed: int, presets: list[str]) -> list[dict]:
    from flowslam.simulation.ground_truth import make_frame
    from flowslam.simulation.raycast import Raycaster
    from flowslam.simulation.sensors import get_sensor

    rows = []
    sensor = get_sensor("hdl64")
    for preset in presets:
        t = time.perf_counter()
        try:
            _, ego, world, actors = _scene(preset, frames, seed, sensor)
        except Exception as e:  # e.g. kitti00-path without the shared data
            print(f"{preset:12s} skipped: {e}")
            continue
        caster = Raycaster(world, actors, sensor)
        n = len(ego.frame_times) - 1
        dyn, pts, inst = np.zeros(n), np.zeros(n), np.zeros(n)
        for k in range(n):
            t0, t1 = float(ego.frame_times[k]), float(ego.frame_times[k + 1])
            f = make_frame(caster.cast(t0, ego.sensor, False), caster, ego.sensor, t0, t1, False,
                           np.random.default_rng(k))
            dyn[k], pts[k] = f.dynamic.sum(), len(f.points)
            inst[k] = len(np.unique(f.instance[f.dynamic]))
        row = {
            "preset": preset, "frames": n, "dynamic_mean": dyn.mean(), "dynamic_median": float(np.median(dyn)),
            "dynamic_min": int(dyn.min()), "dynamic_max": int(dyn.max()), "dynamic_share": dyn.sum() / pts.sum(),
            "moving_objects_mean": inst.mean(), "actors": actors.count_by("role"), "seconds": time.perf_counter() - t,
        }
        rows.append(row)
        print(f"{preset:12s} {n} frames: dynamic points/frame mean {dyn.mean():7.0f} median {np.median(dyn):7.0f} "
              f"min {dyn.min():6.0f} max {dyn.max():6.0f}, share {100 * dyn.sum() / pts.sum():5.2f} %, "
              f"moving objects/frame {inst.mean():5.1f}  ({time.perf_counter() - t:.0f} s)", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("all", "speed", "end-to-end", "presets"), default="all")
    ap.add_argument("--frames", type=int, default=300, help="frames per preset sequence (presets part)")
    ap.add_argument("--speed-frames", type=int, default=30, help="frames per sensor (speed part)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--presets", default="static,dh,dt,rush-hour,kitti00-path")
    ap.add_argument("--json", help="also write the numbers to this file")
    args = ap.parse_args()
    out = {}
    if args.part in ("all", "speed"):
        out["speed"] = bench_speed(args.speed_frames, args.seed)
    if args.part in ("all", "end-to-end"):
        out["end_to_end"] = bench_end_to_end(max(args.speed_frames, 60), args.seed)
    if args.part in ("all", "presets"):
        out["presets"] = bench_presets(args.frames, args.seed, args.presets.split(","))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2, default=float)


if __name__ == "__main__":
    main()
