"""Soak test: a long simulated sequence through a frontend + ``isam2`` s-loam, watching
memory and per-frame time, then a SIGTERM at a random frame and a restart from scratch.

    .venv/bin/python tools/soak.py                       # 4,500 frames, kiss-icp + isam2 s-loam
    .venv/bin/python tools/soak.py --frontend ssf --frames 600 --out results/soak-ssf
    .venv/bin/python tools/soak.py --frontend ssf --frames 1800 --set ssf.lookahead=false  # config overrides

1. Simulates (once; cached like the demo's) the ``kitti00-path`` preset: the real
   KITTI-00 path (3.7 km, real loops) with a town and traffic around it, on a 64-beam
   sensor with ``--columns`` azimuth steps. The simulation runs in a child process, so
   its heap (freed, but kept by the allocator) cannot hide growth in the run's RSS.
2. Runs the sequence (all of it, or ``--max-frames``) in this process
   (``run_sequence``), recording after every frame its wall and CPU time (the CPU time
   of the process, all threads: less sensitive than wall time to a machine shared with
   other jobs), the wall time of each stage (frontend, backend update, loop closer,
   static map; the ``Slam``'s parts wrapped by this tool), the process's resident
   set size (``/proc/self/statm``) and the memory glibc's malloc hands out (``mallinfo2``;
   RSS also holds the free heap glibc keeps); every 100 frames the bytes each part holds (static
   map store, loop closer in memory and spilled, backend scans).
3. Runs ``flowslam run`` on it as a subprocess, sends SIGTERM at a random frame (seeded),
   checks the partial run folder (exit 143, ``run.json`` says why, trajectory of the
   frames done), then runs again from scratch with ``--max-frames`` = the frames the
   stopped run processed, and compares the two trajectories (same inputs, same
   processing: they must agree) and the stopped run's odometry with the full run's.

Writes ``soak.json`` (every number) and ``soak.png`` (RSS and per-frame time vs frame)
into ``--out``; prints a summary. Figures are of this machine; compare runs on one machine.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from flowslam.threads import set_thread_defaults

set_thread_defaults()  # as `flowslam run` does, before numpy, torch and Open3D load

import numpy as np  # noqa: E402

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    """Resident set size of this process now (MB)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 1e6


def simulate_sequence(frames: int, columns: int, seed: int, cache_dir: Path | None) -> Path:
    """The cached sequence, simulated first (in a child process) if it is not there."""
    settings = dict(preset="kitti00-path", frames=frames, seed=seed, columns=columns, workers=os.cpu_count())
    code = ("import sys, json; from flowslam.simulation.demo import ensure_sequence; "
            "a = json.loads(sys.argv[1]); print(ensure_sequence(a['name'], a['settings'], a['cache_dir']))")
    arg = json.dumps(dict(name=f"soak-kitti00-path-{frames}-{columns}-{seed}", settings=settings,
                          cache_dir=None if cache_dir is None else str(cache_dir)))
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, arg], check=True, stdout=subprocess.PIPE, text=True).stdout
    path = Path(out.strip().splitlines()[-1])
    print(f"sequence {path} ({time.perf_counter() - t0:.0f} s to make or find)", flush=True)
    return path


def heap_in_use_mb() -> float | None:
    """Memory glibc's malloc hands out now (MB; ``malloc_in_use_bytes``), None without glibc:
    what the run holds, without the free heap that RSS also counts."""
    from flowslam.sceneflow.network.model import malloc_in_use_bytes

    in_use = malloc_in_use_bytes()
    return None if in_use is None else in_use / 1e6


STAGES = ("frontend", "backend", "loops", "map")


class StageTimer:
    """Wraps the parts of the ``Slam`` that ``run_sequence`` builds (caught by patching
    ``Slam.__init__`` for the duration) to time each stage per frame, and reports the
    bytes the parts hold."""

    def __init__(self):
        self.slam = None
        self.current: dict[str, float] = {}

    def __enter__(self):
        from flowslam.slam import Slam

        self._init = Slam.__init__
        timer = self

        def init(slam, *args, **kwargs):
            timer._init(slam, *args, **kwargs)
            timer.attach(slam)

        Slam.__init__ = init
        return self

    def __exit__(self, *exc):
        from flowslam.slam import Slam

        Slam.__init__ = self._init

    def _wrap(self, fn, stage: str):
        current = self.current

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                current[stage] = current.get(stage, 0.0) + time.perf_counter() - t0

        return timed

    def attach(self, slam) -> None:
        self.slam = slam
        slam.frontend.process = self._wrap(slam.frontend.process, "frontend")
        slam.backend.add_odometry = self._wrap(slam.backend.add_odometry, "backend")
        if hasattr(slam.backend, "add_loop"):
            slam.backend.add_loop = self._wrap(slam.backend.add_loop, "backend")
        if slam.loop_closer is not None:
            slam.loop_closer.add_scan = self._wrap(slam.loop_closer.add_scan, "loops")
        slam.listeners = [self._wrap(listener, "map") for listener in slam.listeners]

    def take(self) -> dict[str, float]:
        """Seconds per stage since the last call."""
        out = {stage: self.current.get(stage, 0.0) for stage in STAGES}
        self.current.clear()
        return out

    def component_bytes(self) -> dict[str, int]:
        slam, out = self.slam, {}
        if slam is None:
            return out
        if slam.map is not None:
            out["map_store"] = slam.map.store.nbytes + slam.map.dynamic.store.nbytes
            recent = getattr(slam.map, "_recent", None)
            out["map_recent_voxels"] = recent.nbytes if recent is not None else 0
        if slam.loop_closer is not None:
            out["loop_closer_memory"] = slam.loop_closer.memory_bytes()
            if hasattr(slam.loop_closer, "disk_bytes"):
                out["loop_closer_disk"] = slam.loop_closer.disk_bytes()
        out["backend_scans"] = len(getattr(slam.backend, "indices", []))
        return out


def run_in_process(sequence: Path, frontend: str, out: Path, max_frames: int | None = None,
                   options: dict | None = None) -> dict:
    """The run, with per-frame wall and CPU time, per-stage time, RSS and component bytes;
    ``options``: dotted config overrides (``{"ssf.lookahead": False}``)."""
    from flowslam.config import load_config
    from flowslam.run import run_sequence

    overrides = dict(options or {}, **({"dataset.max_frames": max_frames} if max_frames else {}))
    cfg = load_config(frontend=frontend, backend="isam2", variant="s-loam", output_dir=str(out / "runs"), **overrides)
    seconds, cpu, rss, heap, stages, components = [], [], [], [], {stage: [] for stage in STAGES}, []
    timer = StageTimer()
    t0 = time.perf_counter()
    last_cpu = [time.process_time()]

    def on_frame(k: int, s: float) -> None:
        seconds.append(s)
        now = time.process_time()
        cpu.append(now - last_cpu[0])
        last_cpu[0] = now
        rss.append(rss_mb())
        heap.append(heap_in_use_mb())
        for stage, t in timer.take().items():
            stages[stage].append(t)
        if k % 100 == 0:
            components.append(dict(frame=k, rss_mb=rss[-1], **timer.component_bytes()))
        if k % 500 == 0:
            in_use = "" if heap[-1] is None else f", malloc in use {heap[-1]:.0f} MB"
            print(f"  frame {k}: {s * 1e3:.0f} ms, RSS {rss[-1]:.0f} MB{in_use}", flush=True)

    with timer:
        outcome = run_sequence(sequence, cfg, on_frame=on_frame, tag=f"soak_{frontend}_full")
    outcome.raise_for_error()
    backend_stats = getattr(timer.slam.backend, "stats", None) if timer.slam is not None else None
    return dict(run_dir=str(outcome.run_dir), wall_s=time.perf_counter() - t0, seconds=seconds, cpu_seconds=cpu,
                rss_mb=rss, heap_in_use_mb=heap, stage_seconds=stages, components=components, metrics=outcome.metrics,
                loops=len(outcome.result.loops), loop_frames=[lc.j for lc in outcome.result.loops],
                backend=_backend_summary(backend_stats))


def _backend_summary(stats: dict | None) -> dict | None:
    if not stats:
        return None
    keys = ("median_update_ms", "p95_update_ms", "max_update_ms", "median_loop_update_ms", "max_loop_update_ms",
            "refine_ms")
    return {k: stats.get(k) for k in keys}


def flowslam(*args) -> list[str]:
    return [sys.executable, "-m", "flowslam", "run", "--no-progress", *map(str, args)]


def sigterm_and_restart(sequence: Path, frontend: str, out: Path, n_frames: int, seed: int) -> dict:
    """SIGTERM the CLI at a random frame; restart from scratch for as many frames; compare."""
    from flowslam.trajectory import read_trajectory

    rng = random.Random(seed)
    target = rng.randrange(n_frames // 10, n_frames * 9 // 10)
    stopped_out = out / "stopped"
    common = ["-f", frontend, "-b", "isam2", "--variant", "s-loam"]
    limit = ["--max-frames", n_frames]  # (the whole sequence unless --max-frames limited the soak)
    for margin in (0.6, 0.3, 0.15):  # a run that finished before the signal: again, signalled earlier
        if stopped_out.exists():
            shutil.rmtree(stopped_out)
        proc = subprocess.Popen(flowslam(*common, *limit, "-o", stopped_out, sequence), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        return_code, stderr = _stop_at(proc, stopped_out, target, margin)
        if return_code != 0:
            break
        print(f"  the run finished before SIGTERM (margin {margin}); again, signalled earlier", flush=True)
    latest = stopped_out / "latest"
    info = json.loads((latest / "run.json").read_text())
    k = info["frames_processed"]
    restart_out = out / "restart"
    subprocess.run(flowslam(*common, "-o", restart_out, "--max-frames", k, sequence), check=True,
                   capture_output=True)
    a = read_trajectory(latest / "trajectory_tum.txt")
    b = read_trajectory(restart_out / "latest" / "trajectory_tum.txt")
    diff = np.linalg.norm(a.positions - b.positions, axis=1) if len(a) == len(b) else None
    return dict(target_frame=target, signal_margin=margin, exit_code=return_code,
                stderr_tail=stderr.strip().splitlines()[-1:], run_json_error=info["error"], complete=info["complete"],
                frames_processed=k,
                restart_frames=len(b), same_length=len(a) == len(b),
                max_position_difference_m=None if diff is None else float(diff.max()))


def _stop_at(proc: subprocess.Popen, out: Path, target: int, margin: float) -> tuple[int, str]:
    """SIGTERM at most about ``target`` frames into the run: the run folder appears when
    the first scan is read; then wait ``margin * target`` / the frame rate the in-process
    run measured (``SOAK_FRAMES_PER_SECOND``); ``margin`` < 1 allows for a subprocess
    that runs faster than the measuring run did (a machine shared with other jobs).
    The exact frame is what ``run.json`` says."""
    while not (out.exists() and any(out.iterdir())):
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    rate = float(os.environ.get("SOAK_FRAMES_PER_SECOND", "0")) or None
    time.sleep(margin * target / rate if rate else 10.0)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=1200)
    return proc.returncode, stderr


def summarize(full: dict, warmup: int, window: int, trim_frames: int) -> dict:
    """Medians over the ``window`` frames after ``warmup`` ("first") and the last
    ``window`` frames ("last"); RSS after warm-up, at the end, its peak and its slope, the
    slopes of its floor and ceiling (minima and maxima per ``trim_frames`` frames) and the
    ceiling per 100 frames; the memory malloc hands out after warm-up, at the end and its
    slope, where glibc tells it."""
    s, rss = np.asarray(full["seconds"]) * 1e3, np.asarray(full["rss_mb"])
    cpu = np.asarray(full["cpu_seconds"]) * 1e3
    n = len(s)
    w = min(warmup, n // 4)
    win = max(min(window, (n - w) // 2), 1)
    first, last = slice(w, w + win), slice(n - win, n)
    half = (w + n) // 2
    stages = {stage: np.asarray(v) * 1e3 for stage, v in full["stage_seconds"].items()}
    heap = _heap_series(full)
    heap_fields = {} if heap is None else dict(
        heap_in_use_mb_after_warmup=float(heap[w]), heap_in_use_mb_end=float(heap[-1]),
        heap_in_use_kb_per_frame_after_warmup=_slope(heap, w) * 1e3,
    )
    low, high = _window_extremes(rss, trim_frames)
    per_100 = max(100 // trim_frames, 1)
    return dict(
        frames=n, wall_s=full["wall_s"], loops=full["loops"], loop_frames=full.get("loop_frames"),
        window_frames=win, first_frames=[w, w + win], last_frames=[n - win, n],
        ms_per_frame_first=float(np.median(s[first])), ms_per_frame_last=float(np.median(s[last])),
        cpu_ms_per_frame_first=float(np.median(cpu[first])), cpu_ms_per_frame_last=float(np.median(cpu[last])),
        stage_ms_first={k: float(np.median(v[first])) for k, v in stages.items() if len(v) == n},
        stage_ms_last={k: float(np.median(v[last])) for k, v in stages.items() if len(v) == n},
        rss_mb_after_warmup=float(rss[w]), rss_mb_end=float(rss[-1]), rss_mb_peak=float(rss.max()),
        rss_kb_per_frame_after_warmup=_slope(rss, w) * 1e3, rss_kb_per_frame_second_half=_slope(rss, half) * 1e3,
        rss_floor_kb_per_frame_after_warmup=_slope(low, w // trim_frames) * 1e3 / trim_frames,
        rss_ceiling_kb_per_frame_after_warmup=_slope(high, w // trim_frames) * 1e3 / trim_frames,
        rss_ceiling_mb_every_100=[float(high[i:i + per_100].max()) for i in range(0, len(high), per_100)],
        **heap_fields, backend=full.get("backend"),
    )


def trim_window(options: dict | None = None) -> int:
    """Frames per window of the RSS floor and ceiling: the run's heap trim period
    (``ssf.network.trim_heap_every`` in ``options``, else its default; the default where the
    run never trims). Between two trims the RSS climbs as the frames touch free heap pages
    again (a saw-tooth of ~300 MB on a 64-beam ``ssf`` run); its minima follow what the run
    holds, its maxima the working set."""
    from flowslam.config.ssf import NetworkStageConfig

    default = NetworkStageConfig().trim_heap_every
    return int((options or {}).get("ssf.network.trim_heap_every", default)) or default


def _window_extremes(series: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """(minimum, maximum) of ``series`` over consecutive ``window``-frame windows (the last,
    shorter one dropped)."""
    n = len(series) // window * window
    blocks = np.asarray(series[:n], float).reshape(-1, window)
    return blocks.min(axis=1), blocks.max(axis=1)


def _heap_series(full: dict) -> np.ndarray | None:
    """Malloc in use per frame (MB), None where the run could not ask glibc."""
    heap = full.get("heap_in_use_mb") or []
    return np.asarray(heap, float) if heap and heap[0] is not None else None


def _slope(series: np.ndarray, start: int) -> float:
    """Least-squares growth per frame of ``series`` from frame ``start`` on (NaN: too few)."""
    if len(series) - start <= 2:
        return float("nan")
    return float(np.polyfit(np.arange(start, len(series)), series[start:], 1)[0])


def plot(full: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b, c) = plt.subplots(3, 1, figsize=(8, 8.5), sharex=True)
    a.plot(full["rss_mb"], lw=1, label="RSS")
    heap = _heap_series(full)
    if heap is not None:
        a.plot(heap, lw=1, label="malloc in use")
    comps = full.get("components") or []
    if comps:
        frames = [r["frame"] for r in comps]
        for key, label in (("map_store", "static map store"), ("loop_closer_memory", "loop closer (memory)")):
            if key in comps[0]:
                a.plot(frames, [r.get(key, 0) / 1e6 for r in comps], lw=1, label=label)
    a.set_ylabel("MB")
    a.set_title(title)
    a.legend(fontsize=8)
    k = 50
    for series, label in ((np.asarray(full["seconds"]) * 1e3, "wall"), (np.asarray(full["cpu_seconds"]) * 1e3, "CPU")):
        if label == "wall":
            b.plot(series, lw=0.3, alpha=0.4, label="wall, per frame")
        if len(series) > k:
            b.plot(np.arange(k - 1, len(series)), np.convolve(series, np.ones(k) / k, mode="valid"), lw=1.3,
                   label=f"{label}, mean of {k}")
    ms = np.asarray(full["seconds"]) * 1e3
    if len(ms) > 10:
        b.set_ylim(0, 1.2 * float(np.percentile(ms, 99.5)))  # (the first frame loads libraries: off scale)
    b.set_ylabel("ms per frame")
    b.legend(fontsize=8)
    m = 101
    for stage, v in full["stage_seconds"].items():
        v = np.asarray(v) * 1e3
        if len(v) > m:
            med = np.array([np.median(v[i:i + m]) for i in range(0, len(v) - m + 1, 10)])
            c.plot(np.arange(m // 2, len(v) - m // 2, 10)[:len(med)], med, lw=1.2, label=stage)
    c.set_yscale("log")
    c.set_ylabel(f"stage ms (median of {m})")
    c.set_xlabel("frame")
    c.legend(fontsize=8, ncol=4)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _overrides(pairs: list[str]) -> dict:
    """``KEY=VALUE`` strings -> {KEY: VALUE}, VALUE parsed as JSON when it is JSON."""
    out = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4500)
    ap.add_argument("--columns", type=int, default=512, help="azimuth steps of the simulated 64-beam sensor")
    ap.add_argument("--frontend", default="kiss-icp")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed and the SIGTERM frame's seed")
    ap.add_argument("--max-frames", type=int, default=None, help="run only the first N frames of the sequence")
    ap.add_argument("--warmup", type=int, default=300, help="frames before RSS is expected flat")
    ap.add_argument("--window", type=int, default=500, help="frames of the first/last medians")
    ap.add_argument("--cache-dir", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=Path("results/soak"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override, e.g. ssf.lookahead=false (VALUE read as JSON, else a string)")
    ap.add_argument("--skip-sigterm", action="store_true")
    ap.add_argument("--sigterm-only", action="store_true",
                    help="only the SIGTERM/restart check, added to the soak.json already in --out")
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    args.out.mkdir(parents=True, exist_ok=True)
    sequence = simulate_sequence(args.frames, args.columns, args.seed, args.cache_dir)
    if args.sigterm_only:
        report = json.loads((args.out / "soak.json").read_text())
        summary = report["summary"]
        os.environ["SOAK_FRAMES_PER_SECOND"] = str(summary["frames"] / summary["wall_s"])
        report["sigterm"] = sigterm_and_restart(sequence, args.frontend, args.out, summary["frames"], args.seed)
        print(json.dumps(report["sigterm"], indent=2), flush=True)
        (args.out / "soak.json").write_text(json.dumps(report, indent=1) + "\n")
        return
    options = _overrides(args.set)
    full = run_in_process(sequence, args.frontend, args.out, args.max_frames, options)
    report = dict(frontend=args.frontend, backend="isam2 s-loam", sequence=str(sequence), columns=args.columns,
                  summary=summarize(full, args.warmup, args.window, trim_window(options)), metrics=full["metrics"],
                  components=full["components"])
    print(json.dumps(report["summary"], indent=2), flush=True)
    plot(full, args.out / "soak.png", f"soak: {args.frontend} + isam2 s-loam, {len(full['seconds'])} frames")
    if not args.skip_sigterm:
        os.environ["SOAK_FRAMES_PER_SECOND"] = str(len(full["seconds"]) / full["wall_s"])
        report["sigterm"] = sigterm_and_restart(sequence, args.frontend, args.out, len(full["seconds"]), args.seed)
        print(json.dumps(report["sigterm"], indent=2), flush=True)
    per_frame = dict(ms=[s * 1e3 for s in full["seconds"]], cpu_ms=[s * 1e3 for s in full["cpu_seconds"]],
                     rss_mb=full["rss_mb"], heap_in_use_mb=full["heap_in_use_mb"],
                     stage_ms={k: [s * 1e3 for s in v] for k, v in full["stage_seconds"].items()})
    (args.out / "soak.json").write_text(json.dumps(dict(report, per_frame=per_frame), indent=1) + "\n")
    print(f"soak.json and soak.png in {args.out}")


if __name__ == "__main__":
    main()
