"""``simulate()``: one call from a preset and a seed to a sequence on disk.

Pipeline: road network (procedural grid, or grown around a given trajectory) ->
ego route and motion -> static town -> traffic simulation (-> keeping the actors that
meet the preset's dynamic-points target, ``selection``) -> for every frame: ray cast
the sweep, compute the ground truth, write the files (``writer``; in two worker
processes for longer sequences) -> scene files and ``manifest.json``. Everything random draws from ``numpy.random.Generator``
streams derived from ``seed``, so the same arguments give byte-identical output.

Time axis: frame ``k`` has timestamp ``frame_times[k]`` (s, frame 0 at 0, 0.1 s apart
for procedural routes, the trajectory's own stamps otherwise); one LiDAR sweep
starts at the timestamp and lasts ``sweep_period``. ``T_world_sensor`` of a frame is
the sensor pose at its timestamp.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import time
from pathlib import Path
from queue import Empty
from typing import Callable

import numpy as np

from flowslam.errors import InputError
from flowslam.simulation import labels
from flowslam.simulation.presets import Preset, get_preset

log = logging.getLogger(__name__)

FORMAT = "flowslam-simulation"
FORMAT_VERSION = 1
SIMULATOR_VERSION = "1.0"
"""Bump when the same arguments would produce different output (invalidates demo caches)."""
FRAME_PERIOD = 0.1


def default_trajectory(name: str) -> Path:
    """A trajectory file from the shared data: ``$FLOWSLAM_DATA/trajectories/NAME`` or
    ``<repo>/../shared/data/trajectories/NAME``."""
    candidates = []
    env = os.environ.get("FLOWSLAM_DATA")
    if env:
        candidates.append(Path(env) / "trajectories" / name)
    repo = Path(__file__).resolve().parents[2]
    candidates.append(repo.parent / "shared" / "data" / "trajectories" / name)
    for c in candidates:
        if c.is_file():
            return c
    raise InputError(candidates[-1], "not found: this preset needs that trajectory file "
                     "(pass trajectory=FILE / --trajectory FILE, or set FLOWSLAM_DATA)")


def _times_beside(path: Path) -> Path | None:
    if "poses" in path.name:
        cand = path.with_name(path.name.replace("poses", "times"))
        if cand.is_file():
            return cand
    return None


def _check_out_dir(out_dir: Path, overwrite: bool) -> bool:
    """Raise if ``out_dir`` may not be written; True if an old simulation is to be replaced."""
    if not out_dir.exists():
        return False
    if not out_dir.is_dir():
        raise InputError(out_dir, "exists and is not a folder")
    if not any(out_dir.iterdir()):
        return False
    if not overwrite:
        raise InputError(out_dir, "is not empty (pass overwrite=True / --overwrite to replace a simulation)")
    if not (out_dir / "manifest.json").is_file() and not (out_dir / "sequences").is_dir():
        raise InputError(out_dir, "is not empty and does not hold a simulated sequence; not overwriting it")
    return True


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    if _check_out_dir(out_dir, overwrite):
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)


def build_scene(preset: Preset, frames: int, seed: int, sensor, *, trajectory=None, trajectory_times=None,
                first_pose: int = 0):
    """Network, ego motion, town and actors of a scenario (no rendering)."""
    from flowslam.simulation.ego_path import loop_route, read_ground_path, trajectory_motion
    from flowslam.simulation.meshes import shape_library
    from flowslam.simulation.roads import grid_network, path_network
    from flowslam.simulation.town import build_town
    from flowslam.simulation.traffic import simulate_traffic
    from flowslam.simulation.traffic_spec import DT

    ss = np.random.SeedSequence([int(seed), 0x5EED])
    net_rng, ego_rng, town_rng, traffic_rng = (np.random.default_rng(s) for s in ss.spawn(4))
    if trajectory is not None or preset.route == "trajectory":
        path = Path(trajectory) if trajectory is not None else default_trajectory(preset.trajectory)
        times_path = trajectory_times if trajectory_times is not None else _times_beside(path)
        t, x, y, yaw = read_ground_path(path, times_path)
        if first_pose < 0 or first_pose >= len(t) - 1:
            raise InputError(path, f"first pose {first_pose} is outside the trajectory's {len(t)} poses")
        ego = trajectory_motion(t, x, y, yaw, frames, sensor.vehicle_center_x, first=first_pose)
        # the network covers the driven part of the route (+ what the convoy and the sensor see ahead)
        s_end = float(ego.s_at(ego.frame_times[-1])) + 60.0
        route_part = ego.route.sub(0.0, min(s_end, ego.route.length), step=0.5)
        net = path_network(route_part, net_rng)
        grid_shape = None
    else:
        net = grid_network(net_rng, *preset.grid, block=preset.block)
        grid_shape = preset.grid
        ego = loop_route(net, grid_shape, ego_rng, frames, FRAME_PERIOD, preset.cruise, sensor.vehicle_center_x,
                         extra_time=15.0)
    world = build_town(net, town_rng, preset.town, ego_route=ego.route)
    t_end = float(ego.frame_times[-1]) + sensor.sweep_period + DT
    actors = simulate_traffic(net, world, ego, preset.traffic, shape_library(), traffic_rng, t_end,
                              despawn_distance=sensor.max_range + 30.0, ego_size=sensor.vehicle_size)
    if preset.traffic.target_dynamic is not None:
        from flowslam.simulation.selection import select_actors

        actors.stats["selection"] = select_actors(world, actors, ego, preset.traffic.target_dynamic)
    return net, ego, world, actors


def simulate(
    out_dir: str | Path,
    preset: str = "dt",
    frames: int | None = None,
    seed: int = 0,
    sensor: str | None = None,
    *,
    columns: int | None = None,
    max_range: float | None = None,
    range_noise: float | None = None,
    dropout: float | None = None,
    distortion: bool = False,
    trajectory: str | Path | None = None,
    trajectory_times: str | Path | None = None,
    first_pose: int = 0,
    overwrite: bool = False,
    compress: bool = True,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Simulate a sequence into ``out_dir`` (KITTI layout + ground truth, see ``writer``).

    Args:
        preset: ``static``, ``dh``, ``dt``, ``rush-hour``, ``kitti00-path`` or ``demo``.
        frames: number of frames (default: the preset's; for a trajectory, at most its
            poses minus one).
        seed: everything random derives from it (same seed, same bytes).
        sensor: ``hdl64``, ``av2``, ``vlp32c``, ``vlp16``, ``os1-128`` (default: the preset's).
        columns, max_range, range_noise, dropout: sensor options (``SensorModel``).
        distortion: move the sensor and the actors during the sweep (per-column timing).
        trajectory, trajectory_times, first_pose: drive along a given trajectory file
            (KITTI camera-0 or z-up poses, see ``ego_path``) instead of a procedural route;
            ``kitti00-path`` defaults to the shared KITTI-00 ground truth. A times file
            named like the poses file with ``poses`` -> ``times`` is picked up.
        overwrite: replace an existing simulation in ``out_dir``.
        compress: deflate the ground-truth ``.npz`` files (level 1).
        workers: rendering processes (default: 2 on a machine with 2+ cores for 60+ frames,
            else 1 = in this process); the output does not depend on it.
        progress: ``progress(done, total)`` after every frame.

    Returns the manifest (also written to ``out_dir/manifest.json``).
    """
    from flowslam.simulation.paths import planar_T
    from flowslam.simulation.scene_io import save_actors, save_town
    from flowslam.simulation.sensors import get_sensor
    from flowslam.simulation.writer import SequenceWriter, write_json
    from flowslam import geometry

    started = time.perf_counter()
    p = get_preset(preset)
    sensor_model = get_sensor(sensor or p.sensor, columns=columns if columns is not None else
                              (p.columns if sensor is None else None), max_range=max_range,
                              range_noise=range_noise, dropout=dropout)
    frames = p.frames if frames is None else int(frames)
    if not 1 <= frames <= 100_000:
        raise InputError(None, f"frames must be in 1..100000, got {frames}")
    out_dir = Path(out_dir)
    _check_out_dir(out_dir, overwrite)  # fail early; nothing is removed before the scene is built
    net, ego, world, actors = build_scene(p, frames, seed, sensor_model, trajectory=trajectory,
                                          trajectory_times=trajectory_times, first_pose=first_pose)
    _prepare_out_dir(out_dir, overwrite)
    frames = len(ego.frame_times) - 1
    scene_s = time.perf_counter() - started
    render_started = time.perf_counter()
    counts = _render(out_dir, world, actors, sensor_model, ego, distortion, seed, frames, compress, progress,
                     workers)
    n_points, n_dynamic, dyn_instances, per_class = counts
    x, y, yaw = ego.sensor.at(ego.frame_times[:frames])
    T_town = planar_T(x, y, yaw, sensor_model.ground_height)
    T_first = T_town[0]
    poses_rel = geometry.inv(T_first)[None] @ T_town
    SequenceWriter(out_dir, compress=compress, threaded=False).finish(poses_rel, ego.frame_times[:frames])
    render_s = time.perf_counter() - render_started
    seq = out_dir / "sequences" / "00"
    save_actors(seq / "actors.npz", ego.sensor, actors, T_first, sensor_model.ground_height)
    save_town(seq / "town.npz", world)
    manifest = _manifest(p, seed, frames, sensor_model, distortion, ego, actors, world, n_points, n_dynamic,
                         dyn_instances, per_class, T_first, trajectory, scene_s, render_s)
    write_json(out_dir / "manifest.json", manifest)
    manifest["timing_s"] = {"scene": round(scene_s, 2), "render_and_write": round(render_s, 2),
                            "frames_per_s": round(frames / max(render_s, 1e-9), 2)}
    log.info("simulated %d frames into %s (%.1f frames/s)", frames, out_dir, frames / max(render_s, 1e-9))
    return manifest


def _stats(a: np.ndarray) -> dict:
    return {"mean": float(a.mean()), "min": int(a.min()), "max": int(a.max()), "median": float(np.median(a))}


def _manifest(p, seed, frames, sensor, distortion, ego, actors, world, n_points, n_dynamic, dyn_instances,
              per_class, T_first, trajectory, scene_s, render_s) -> dict:
    import open3d
    import flowslam

    path = np.array(ego.sensor.at(ego.frame_times[:frames])[:2]).T
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) if frames > 1 else 0.0
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "generator": {
            "simulator": SIMULATOR_VERSION,
            "flowslam": flowslam.__version__,
            "numpy": np.__version__,
            "open3d": open3d.__version__,
        },
        "preset": p.name,
        "preset_description": p.description,
        "dynamic_target": p.dynamic_target,
        "seed": int(seed),
        "frames": int(frames),
        "sequence": "00",
        "frame_period_s": FRAME_PERIOD if trajectory is None and p.route != "trajectory" else None,
        "distortion": bool(distortion),
        "sensor": sensor.to_dict(),
        "route": {"description": ego.description, "length_m": round(length, 3),
                  "trajectory": None if trajectory is None else str(trajectory)},
        "conventions": {
            "frames": "sensor frame: x forward, y left, z up; poses/00.txt = T_world_sensor at each frame "
                      "timestamp, world = the first frame's sensor frame; calib Tr = identity (the LiDAR is "
                      "the 'camera 0' frame)",
            "points": "each point in the sensor frame at its own firing time (t + times[i]); without "
                      "distortion all points at the frame timestamp (times = 0)",
            "flow": "Argoverse 2: p + flow = the same physical point at the next frame's timestamp + the "
                    "same firing offset, in the sensor frame of that instant",
            "flow_compensated": "the object's own motion only, in the sensor frame at the point's firing time "
                                "(zero for static points)",
            "dynamic": "world speed of the point > 0.5 m/s",
            "instances": "-1 = ground; static things 1..; moving actors from %d" % labels.ACTOR_ID_BASE,
        },
        "classes": labels.class_table(),
        "actors": {
            "count": len(actors.actors),
            "by_shape_kind": actors.count_by("shape"),
            "by_role": actors.count_by("role"),
            "removed_for_overlap": int(actors.removed),
            "selection": actors.stats.get("selection"),
        },
        "static_instances": int(len(world.instance_class) - 1),
        "stats": {
            "points_per_frame": _stats(n_points),
            "dynamic_points_per_frame": _stats(n_dynamic),
            "dynamic_share": float(n_dynamic.sum() / max(n_points.sum(), 1)),
            "dynamic_instances_per_frame": _stats(dyn_instances),
            "points_per_class": {labels.CLASS_NAMES[i]: int(c) for i, c in enumerate(per_class) if c},
            "dynamic_points": [int(v) for v in n_dynamic],
        },
        "T_town_first": np.round(T_first, 9).tolist(),
    }


def settings_hash(**settings) -> str:
    """Short hash of simulation settings and the simulator version (cache keys)."""
    text = repr(sorted(settings.items())) + SIMULATOR_VERSION
    return hashlib.sha256(text.encode()).hexdigest()[:12]


# ------------------------------------------------------------------ rendering
def _render_share(out_dir, world, actors, sensor, ego, distortion, seed, frame_ids, compress, report) -> None:
    """Render and write the frames ``frame_ids``; ``report(k, counts)`` after each."""
    from flowslam.simulation.ground_truth import make_frame
    from flowslam.simulation.raycast import Raycaster
    from flowslam.simulation.writer import SequenceWriter

    caster = Raycaster(world, actors, sensor)
    writer = SequenceWriter(out_dir, compress=compress)
    try:
        for k in frame_ids:
            t0, t1 = float(ego.frame_times[k]), float(ego.frame_times[k + 1])
            raw = caster.cast(t0, ego.sensor, distortion)
            frame = make_frame(raw, caster, ego.sensor, t0, t1, distortion, np.random.default_rng([int(seed), 0xF4A3E, k]))
            writer.write(k, frame)
            report(k, (len(frame.points), int(frame.dynamic.sum()), len(np.unique(frame.instance[frame.dynamic])),
                       np.bincount(frame.cls, minlength=labels.NUM_CLASSES)))
    finally:
        writer.close()


def _worker(args, queue) -> None:
    try:
        _render_share(*args, report=lambda k, c: queue.put(("frame", k, c)))
        queue.put(("done", None, None))
    except BaseException as e:  # sent to the parent, which raises it
        import traceback

        queue.put(("error", None, f"{e.__class__.__name__}: {e}\n{traceback.format_exc()}"))


def _render(out_dir, world, actors, sensor, ego, distortion, seed, frames, compress, progress, workers):
    n_points = np.zeros(frames, dtype=np.int64)
    n_dynamic = np.zeros(frames, dtype=np.int64)
    dyn_instances = np.zeros(frames, dtype=np.int64)
    per_class = np.zeros(labels.NUM_CLASSES, dtype=np.int64)
    done = [0]

    def take(k, c):
        n_points[k], n_dynamic[k], dyn_instances[k] = c[0], c[1], c[2]
        per_class[:] += c[3]
        done[0] += 1
        if progress is not None:
            progress(done[0], frames)

    if workers is None:
        workers = 2 if (os.cpu_count() or 1) >= 2 and frames >= 60 else 1
    workers = max(1, min(int(workers), frames))
    if workers == 1:
        _render_share(out_dir, world, actors, sensor, ego, distortion, seed, range(frames), compress, take)
        return n_points, n_dynamic, dyn_instances, per_class
    import multiprocessing as mp

    ctx = mp.get_context("spawn")  # fork is unsafe once Open3D/TBB threads exist
    queue = ctx.Queue()
    procs = [
        ctx.Process(target=_worker, args=((out_dir, world, actors, sensor, ego, distortion, seed,
                                            range(w, frames, workers), compress), queue), daemon=True)
        for w in range(workers)
    ]
    for p in procs:
        p.start()
    finished = 0
    try:
        while finished < workers:
            try:
                kind, k, payload = queue.get(timeout=5.0)
            except Empty:  # nothing for 5 s: carry on unless a worker died without reporting
                dead = [p for p in procs if not p.is_alive() and p.exitcode not in (0, None)]
                if dead or not any(p.is_alive() for p in procs):
                    raise RuntimeError(
                        "a simulation worker process died without reporting (exit code "
                        f"{dead[0].exitcode if dead else '?'}); simulate(..., workers=1) renders in this process"
                    ) from None
                continue
            if kind == "frame":
                take(k, payload)
            elif kind == "done":
                finished += 1
            else:
                raise RuntimeError(f"simulation worker failed: {payload}")
    finally:
        for p in procs:
            if p.is_alive() and finished < workers:
                p.terminate()
            p.join()
    return n_points, n_dynamic, dyn_instances, per_class
