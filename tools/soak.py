"""Soak test: a long simulated sequence through a frontend + ``isam2`` s-loam, watching
memory and per-frame time, then a SIGTERM at a random frame and a restart from scratch.

    .venv/bin/python tools/soak.py                       # 4,500 frames, kiss-icp + isam2 s-loam
    .venv/bin/python tools/soak.py --frontend ssf --frames 600 --out results/soak-ssf

1. Simulates (once; cached like the demo's) the ``kitti00-path`` preset: the real
   KITTI-00 path (3.7 km, real loops) with a town and traffic around it, on a 64-beam
   sensor with ``--columns`` azimuth steps.
2. Runs the whole sequence in this process (``run_sequence``), recording after every
   frame its wall time and the process's resident set size (``/proc/self/statm``).
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
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    """Resident set size of this process now (MB)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 1e6


def simulate_sequence(frames: int, columns: int, seed: int, cache_dir: Path | None) -> Path:
    from flowslam.simulation.demo import ensure_sequence

    settings = dict(preset="kitti00-path", frames=frames, seed=seed, columns=columns, workers=os.cpu_count())
    t0 = time.perf_counter()
    path = ensure_sequence(f"soak-kitti00-path-{frames}-{columns}-{seed}", settings, cache_dir)
    print(f"sequence {path} ({time.perf_counter() - t0:.0f} s to make or find)", flush=True)
    return path


def run_in_process(sequence: Path, frontend: str, out: Path) -> dict:
    """The full run, with per-frame wall time and RSS."""
    from flowslam.config import load_config
    from flowslam.run import run_sequence

    cfg = load_config(frontend=frontend, backend="isam2", variant="s-loam", output_dir=str(out / "runs"))
    seconds, rss = [], []
    t0 = time.perf_counter()

    def on_frame(k: int, s: float) -> None:
        seconds.append(s)
        rss.append(rss_mb())
        if k % 500 == 0:
            print(f"  frame {k}: {s * 1e3:.0f} ms, RSS {rss[-1]:.0f} MB", flush=True)

    outcome = run_sequence(sequence, cfg, on_frame=on_frame, tag=f"soak_{frontend}_full")
    outcome.raise_for_error()
    return dict(run_dir=str(outcome.run_dir), wall_s=time.perf_counter() - t0, seconds=seconds, rss_mb=rss,
                metrics=outcome.metrics, loops=len(outcome.result.loops))


def flowslam(*args) -> list[str]:
    return [sys.executable, "-m", "flowslam", "run", "--no-progress", *map(str, args)]


def sigterm_and_restart(sequence: Path, frontend: str, out: Path, n_frames: int, seed: int) -> dict:
    """SIGTERM the CLI at a random frame; restart from scratch for as many frames; compare."""
    from flowslam.trajectory import read_trajectory

    rng = random.Random(seed)
    target = rng.randrange(n_frames // 10, n_frames * 9 // 10)
    stopped_out = out / "stopped"
    common = ["-f", frontend, "-b", "isam2", "--variant", "s-loam"]
    proc = subprocess.Popen(flowslam(*common, "-o", stopped_out, sequence), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return_code, stderr = _stop_at(proc, stopped_out, target)
    latest = stopped_out / "latest"
    info = json.loads((latest / "run.json").read_text())
    k = info["frames_processed"]
    restart_out = out / "restart"
    subprocess.run(flowslam(*common, "-o", restart_out, "--max-frames", k, sequence), check=True,
                   capture_output=True)
    a = read_trajectory(latest / "trajectory_tum.txt")
    b = read_trajectory(restart_out / "latest" / "trajectory_tum.txt")
    diff = np.linalg.norm(a.positions - b.positions, axis=1) if len(a) == len(b) else None
    return dict(target_frame=target, exit_code=return_code, stderr_tail=stderr.strip().splitlines()[-1:],
                run_json_error=info["error"], complete=info["complete"], frames_processed=k,
                restart_frames=len(b), same_length=len(a) == len(b),
                max_position_difference_m=None if diff is None else float(diff.max()))


def _stop_at(proc: subprocess.Popen, out: Path, target: int) -> tuple[int, str]:
    """SIGTERM about ``target`` frames into the run: the run folder appears when the
    first scan is read; then wait ``target`` / the frame rate the in-process run
    measured (``SOAK_FRAMES_PER_SECOND``). The exact frame is what ``run.json`` says."""
    while not (out.exists() and any(out.iterdir())):
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    rate = float(os.environ.get("SOAK_FRAMES_PER_SECOND", "0")) or None
    time.sleep(target / rate if rate else 10.0)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=600)
    return proc.returncode, stderr


def summarize(full: dict, warmup: int) -> dict:
    s, rss = np.asarray(full["seconds"]) * 1e3, np.asarray(full["rss_mb"])
    n = len(s)
    w = min(warmup, n // 4)
    tail = max(n // 10, 1)
    after = rss[w:]
    slope = np.polyfit(np.arange(w, n), after, 1)[0] if len(after) > 2 else float("nan")
    return dict(
        frames=n, wall_s=full["wall_s"], loops=full["loops"],
        ms_per_frame_first=float(np.median(s[w:w + tail])), ms_per_frame_last=float(np.median(s[-tail:])),
        rss_mb_after_warmup=float(rss[w]), rss_mb_end=float(rss[-1]), rss_mb_peak=float(rss.max()),
        rss_kb_per_frame_after_warmup=float(slope * 1e3),
    )


def plot(full: dict, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a.plot(full["rss_mb"], lw=1)
    a.set_ylabel("RSS (MB)")
    a.set_title(title)
    ms = np.asarray(full["seconds"]) * 1e3
    b.plot(ms, lw=0.3, alpha=0.5, label="per frame")
    k = 50
    if len(ms) > k:
        b.plot(np.arange(k - 1, len(ms)), np.convolve(ms, np.ones(k) / k, mode="valid"), lw=1.5,
               label=f"mean of {k}")
    b.set_ylabel("ms per frame")
    b.set_xlabel("frame")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4500)
    ap.add_argument("--columns", type=int, default=512, help="azimuth steps of the simulated 64-beam sensor")
    ap.add_argument("--frontend", default="kiss-icp")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed and the SIGTERM frame's seed")
    ap.add_argument("--warmup", type=int, default=300, help="frames before RSS is expected flat")
    ap.add_argument("--cache-dir", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=Path("results/soak"))
    ap.add_argument("--skip-sigterm", action="store_true")
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    args.out.mkdir(parents=True, exist_ok=True)
    sequence = simulate_sequence(args.frames, args.columns, args.seed, args.cache_dir)
    full = run_in_process(sequence, args.frontend, args.out)
    report = dict(frontend=args.frontend, backend="isam2 s-loam", sequence=str(sequence), columns=args.columns,
                  summary=summarize(full, args.warmup), metrics=full["metrics"])
    print(json.dumps(report["summary"], indent=2), flush=True)
    plot(full, args.out / "soak.png", f"soak: {args.frontend} + isam2 s-loam, {len(full['seconds'])} frames")
    if not args.skip_sigterm:
        os.environ["SOAK_FRAMES_PER_SECOND"] = str(len(full["seconds"]) / full["wall_s"])
        report["sigterm"] = sigterm_and_restart(sequence, args.frontend, args.out, len(full["seconds"]), args.seed)
        print(json.dumps(report["sigterm"], indent=2), flush=True)
    (args.out / "soak.json").write_text(json.dumps(dict(report, per_frame=dict(
        ms=[s * 1e3 for s in full["seconds"]], rss_mb=full["rss_mb"])), indent=1) + "\n")
    print(f"soak.json and soak.png in {args.out}")


if __name__ == "__main__":
    main()
