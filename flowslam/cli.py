"""The ``flowslam`` command line (typer). Heavy modules are imported inside commands.

Bad input (``InputError``) prints one line, ``flowslam: error: FILE: problem``, and
exits with code 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(
    name="flowslam",
    help="LiDAR SLAM with scene flow as odometry, on a GTSAM factor graph.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)

_state = {"debug": False}


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)


@app.callback()
def _main(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logs."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only warnings and errors."),
):
    _state["debug"] = debug
    # Before torch loads OpenMP: spinning OpenMP threads turn a 0.1 s forward pass into
    # seconds when the cores are shared (2-core machines); a user's own setting wins.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from rich.logging import RichHandler

    level = logging.DEBUG if debug else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(
        level=level, format="%(message)s", force=True,
        handlers=[RichHandler(console=_stderr_console(), show_path=debug, show_time=False)],
    )


@contextmanager
def _user_errors():
    """Turn ``InputError`` into one line on stderr and exit code 2 (unless --debug). So
    too an ``OSError`` that names a file (a folder that cannot be made, no permission,
    no space left): a problem of the machine or of the paths given, not of flowslam."""
    from flowslam.errors import InputError

    try:
        yield
    except (InputError, OSError) as error:
        if _state["debug"] or (isinstance(error, OSError) and not error.filename):
            raise
        if isinstance(error, OSError):
            error = InputError(error.filename, error.strerror or str(error))
        print(f"flowslam: error: {error}", file=sys.stderr)
        raise typer.Exit(code=2) from None


def _progress():
    from rich.progress import (
        BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[fps]:>6.1f} frames/s"), TimeElapsedColumn(),
        TimeRemainingColumn(), console=_stderr_console(), transient=False,
    )


def _progress_callbacks(bar, label: str):
    """``on_start(n)`` / ``on_frame(k, seconds)`` that drive ``bar`` with the mean frames/s so far."""
    state = {"task": None, "seconds": 0.0}

    def on_start(n: int) -> None:
        state["task"] = bar.add_task(label, total=n, fps=0.0)

    def on_frame(k: int, seconds: float) -> None:
        state["seconds"] += seconds
        bar.update(state["task"], advance=1, fps=(k + 1) / max(state["seconds"], 1e-9))

    return on_start, on_frame


@app.command()
def run(
    sequence: Path = typer.Argument(..., help="Sequence: KITTI folder, scan folder, ROS bag, AV2 log."),
    frontend: Optional[str] = typer.Option(
        None, "--frontend", "-f",
        help="Frontend (default kiss-icp): kiss-icp, ransac, ssf, sf (learned flow, no segmentation); ablations that "
             "read ground truth, SSF-PAN markers: gt (GT flow + GT segmentation), gt-flow (GT flow, none), "
             "gt-seg (◐ ssf's flow + GT segmentation), gt-flow+ssf-seg (○ GT flow + ssf's segmentation)."),
    backend: Optional[str] = typer.Option(None, "--backend", "-b", help="Backend name (default odometry)."),
    variant: Optional[str] = typer.Option(
        None, "--variant", help="a-loam (odometry only) or s-loam (loop closure, default; backends that take loops)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config (see `flowslam config`)."),
    output_dir: Optional[Path] = typer.Option(None, "--output-dir", "-o", help="Where run folders go (default results/)."),
    fmt: Optional[str] = typer.Option(None, "--format", help="Force the reader: kitti, folder, rosbag, argoverse2."),
    topic: Optional[str] = typer.Option(None, "--topic", help="ROS bags: the PointCloud2 topic."),
    gt_topic: Optional[str] = typer.Option(None, "--gt-topic", help="ROS bags: Odometry/PoseStamped GT topic."),
    sequence_id: Optional[str] = typer.Option(None, "--sequence", help="KITTI sequence id (e.g. 00)."),
    poses: Optional[Path] = typer.Option(None, "--poses", help="Scan folders: GT poses file (KITTI or TUM)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="ssf: a weights file instead of the shipped one."),
    kitti_correction: Optional[float] = typer.Option(
        None, "--kitti-correction-deg", help="KITTI beam elevation correction (default 0.205; 0 = off)."),
    first: Optional[int] = typer.Option(None, "--first", help="First frame index."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", "-n", help="Process at most N frames."),
    fix_times: bool = typer.Option(
        False, "--fix-times", help="Repair scan timestamps that do not increase strictly (logged) instead of stopping."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
):
    """Estimate the trajectory of SEQUENCE and write it (TUM, KITTI), metrics and a plot."""
    from flowslam.signals import terminate_as_interrupt

    with _user_errors(), _stopped_by_signal(), terminate_as_interrupt():
        from flowslam.config import load_config

        overrides = {
            "ssf.network.weights": weights and str(weights),
            "dataset.format": fmt, "dataset.topic": topic, "dataset.gt_topic": gt_topic,
            "dataset.sequence": sequence_id, "dataset.poses": poses and str(poses),
            "dataset.kitti_vertical_correction_deg": kitti_correction,
            "dataset.first_frame": first, "dataset.max_frames": max_frames,
            "dataset.fix_times": fix_times or None,
        }
        cfg = load_config(
            config, frontend=frontend, backend=backend, output_dir=output_dir and str(output_dir), variant=variant,
            **overrides,
        )
        requested = [key for key, value in overrides.items() if value is not None]
        if variant is not None:
            requested.append("loop_closure.enabled")
        from flowslam.run import run_sequence

        if no_progress:
            outcome = run_sequence(sequence, cfg, requested=requested)
        else:
            with _progress() as bar:
                on_start, on_frame = _progress_callbacks(bar, cfg.frontend)
                outcome = run_sequence(sequence, cfg, on_start=on_start, on_frame=on_frame, requested=requested)
        _report_run(outcome)
        outcome.raise_for_error()


@contextmanager
def _stopped_by_signal():
    """Ctrl-C or SIGTERM (after the run folder is written): one line, exit 128 + signal."""
    from flowslam.signals import describe_stop, exit_code

    try:
        yield
    except KeyboardInterrupt as stop:
        if _state["debug"]:
            raise
        print(f"flowslam: {describe_stop(stop)}", file=sys.stderr)
        raise typer.Exit(code=exit_code(stop)) from None


def _report_run(outcome) -> None:
    from rich.console import Console

    console = Console()
    result = outcome.result
    if outcome.metrics is not None:
        from flowslam.evaluation import render_table

        console.print(render_table(outcome.metrics))
    console.print(
        f"{len(result.indices)} frames, {result.frames_per_second:.1f} frames/s; "
        f"results in [bold]{outcome.run_dir}[/bold]"
    )
    if result.error is not None:
        kept = (f"the trajectory of the {len(result.indices)} frames before it is written" if result.indices
                else "no frame was processed, so there is no trajectory (run.json says why)")
        console.print(f"[yellow]stopped at frame {result.failed_index}; {kept}.[/yellow]")


@app.command("eval")
def evaluate_command(
    estimate: Path = typer.Argument(..., help="Estimated trajectory (TUM or KITTI file)."),
    ground_truth: Path = typer.Argument(..., help="Ground-truth trajectory (TUM or KITTI file)."),
    max_diff: float = typer.Option(0.01, "--max-diff", help="Max timestamp difference (s) for association."),
    offset: float = typer.Option(0.0, "--offset", help="Seconds added to the estimate's timestamps."),
    delta: list[str] = typer.Option(["1"], "--delta", help="RPE deltas: N (frames) or Nm (metres); repeatable."),
    no_align: bool = typer.Option(False, "--no-align", help="APE without Umeyama SE(3) alignment."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the metrics as JSON."),
):
    """Compare an estimated trajectory with ground truth: APE, RPE, KITTI drift, Table I stats."""
    with _user_errors():
        from rich.console import Console

        from flowslam.errors import InputError
        from flowslam.evaluation import evaluate, render_table
        from flowslam.trajectory import read_trajectory

        deltas = []
        for d in delta:
            unit = "m" if d.endswith("m") else "frames"
            try:
                value = float(d[:-1]) if unit == "m" else int(d)
            except ValueError:
                raise InputError(None, f"--delta {d!r}: use an integer (frames) or a number + 'm'") from None
            if value <= 0:
                raise InputError(None, f"--delta {d!r} must be positive")
            deltas.append((value, unit))
        est, gt = read_trajectory(estimate), read_trajectory(ground_truth)
        metrics = evaluate(
            est, gt, max_diff=max_diff, offset=offset, rpe_deltas=tuple(deltas),
            align=not no_align, est_name=str(estimate), gt_name=str(ground_truth),
        )
        Console().print(render_table(metrics))
        if json_out is not None:
            from flowslam.results import write_json

            write_json(json_out, metrics)


@app.command("simulate")
def simulate_command(
    out_dir: Path = typer.Argument(..., help="Output folder (KITTI layout + GT + manifest.json)."),
    preset: str = typer.Option("dt", "--preset", "-p", help="static, dh, dt, rush-hour, kitti00-path, demo."),
    frames: Optional[int] = typer.Option(None, "--frames", "-n", help="Number of scans (default: the preset's)."),
    seed: int = typer.Option(0, "--seed", help="Town, traffic and noise seed (same seed = same output)."),
    sensor: Optional[str] = typer.Option(None, "--sensor", "-s", help="hdl64, av2, vlp32c, vlp16, os1-128."),
    columns: Optional[int] = typer.Option(None, "--columns", help="Azimuth steps per revolution."),
    max_range: Optional[float] = typer.Option(None, "--max-range", help="Maximum range (m)."),
    noise: Optional[float] = typer.Option(None, "--noise", help="Range noise, 1 sigma (m)."),
    dropout: Optional[float] = typer.Option(None, "--dropout", help="Share of returns dropped at random."),
    distortion: bool = typer.Option(False, "--distortion/--no-distortion", help="Motion during the sweep."),
    trajectory: Optional[Path] = typer.Option(None, "--trajectory", help="Drive along this KITTI/TUM trajectory."),
    trajectory_times: Optional[Path] = typer.Option(None, "--trajectory-times", help="times.txt for --trajectory."),
    first_pose: int = typer.Option(0, "--first-pose", help="Start at this pose of --trajectory."),
    preview: bool = typer.Option(False, "--preview", help="Write preview.png (top view by class and flow)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output folder."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Rendering processes (default: cores)."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
):
    """Simulate a LiDAR sequence with exact GT poses, scene flow, classes and instances."""
    with _user_errors():
        from flowslam.simulation import simulate, write_preview

        kwargs = dict(
            preset=preset, frames=frames, seed=seed, sensor=sensor, columns=columns,
            max_range=max_range, range_noise=noise, dropout=dropout, distortion=distortion,
            trajectory=trajectory, trajectory_times=trajectory_times, first_pose=first_pose,
            overwrite=overwrite, workers=workers,
        )
        if no_progress:
            manifest = simulate(out_dir, **kwargs)
        else:
            with _progress() as bar:
                task = bar.add_task("simulate", total=None, fps=0.0)
                t0 = time.perf_counter()
                manifest = simulate(out_dir, **kwargs, progress=lambda done, total: bar.update(
                    task, completed=done, total=total, fps=done / max(time.perf_counter() - t0, 1e-9)))
        stats = manifest.get("stats", {})
        typer.echo(
            f"{manifest['frames']} frames of {manifest['sensor']['name']} ({manifest['preset']}, seed {seed}) in {out_dir}: "
            f"{stats.get('points_per_frame', {}).get('mean', float('nan')):.0f} points and "
            f"{stats.get('dynamic_points_per_frame', {}).get('mean', float('nan')):.0f} dynamic points per frame"
        )
        if preview:
            typer.echo(f"preview: {write_preview(out_dir)}")


@app.command("demo")
def demo_command(
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Where the demo sequence is cached."),
    refresh: bool = typer.Option(False, "--refresh", help="Simulate the demo sequence again."),
    output_dir: Path = typer.Option(Path("results"), "--output-dir", "-o", help="Where run folders go."),
    frontends: Optional[list[str]] = typer.Option(
        None, "--frontend", "-f", help="These frontends (repeatable; default kiss-icp, ssf, gt, gt-flow)."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bars."),
):
    """No data needed: simulate the default sequence once, run the main frontends x backends, print errors."""
    with _user_errors():
        from rich.console import Console

        from flowslam.config import load_config
        from flowslam.demo import DEMO_FRONTENDS, demo_failures, demo_table, run_demo
        from flowslam.results import create_results_dir, link_latest
        from flowslam.simulation import ensure_demo_sequence

        if not _state["debug"]:  # per-loop and per-run INFO lines would bury the table
            logging.getLogger("flowslam").setLevel(logging.WARNING)
        t0 = time.perf_counter()
        sequence = ensure_demo_sequence(cache_dir, refresh=refresh)
        demo_dir = create_results_dir(output_dir, "demo")
        link_latest(demo_dir)
        cfg = load_config(output_dir=str(demo_dir))
        chosen = frontends or list(DEMO_FRONTENDS)
        if no_progress:
            rows = run_demo(sequence, cfg, chosen)
        else:
            with _progress() as bar:
                rows = run_demo(sequence, cfg, chosen, progress=lambda label, n: _progress_callbacks(bar, label))
        Console().print(demo_table(rows))
        for line in demo_failures(rows):
            typer.echo(f"not run: {line}", err=True)
        typer.echo(f"sequence {sequence}; runs and plots in {demo_dir}; {time.perf_counter() - t0:.0f} s in all")


@app.command("bench")
def bench_command(
    sequences: Optional[list[Path]] = typer.Option(
        None, "--sequence", "-s", help="Also run on this sequence (repeatable; any format `run` reads)."),
    frontends: Optional[list[str]] = typer.Option(
        None, "--frontend", "-f", help="Only these frontends (repeatable; default: every baseline and ablation)."),
    no_default_suite: bool = typer.Option(False, "--no-default-suite", help="Only the --sequence ones."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Shorten the default suite's sequences (quick look)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config applied to every run."),
    output_dir: Path = typer.Option(Path("results"), "--output-dir", "-o", help="Where the bench folder goes."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Go on with the unfinished bench in this folder."),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Where simulated sequences are cached."),
    jobs: Optional[int] = typer.Option(
        None, "--jobs", "-j", min=1, help="Cells run at once, one OpenMP thread each when > 1 (default 1)."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bars."),
):
    """Frontends x (a-loam, s-loam) x sequences: SSF-PAN Table I, runtime vs RPE, trajectories."""
    with _user_errors():
        from flowslam.benchmark.runner import BenchStopped, run_bench, start_bench
        from flowslam.benchmark.suite import DEFAULT_FRONTENDS, default_sequences
        from flowslam.config import load_config
        from flowslam.errors import InputError
        from flowslam.registry import frontend_names
        from flowslam.results import create_results_dir, link_latest

        t0 = time.perf_counter()
        if resume is not None:
            if sequences or frontends or no_default_suite or frames or config:
                raise InputError(resume, "--resume goes on with the bench as it was started; give no other choices")
            bench_dir = resume
        else:
            chosen = list(frontends or DEFAULT_FRONTENDS)
            unknown = sorted(set(chosen) - set(frontend_names()))
            if unknown:
                raise InputError(None, f"unknown frontend(s) {', '.join(unknown)}; available: {', '.join(frontend_names())}")
            cfg = load_config(config)
            runs: dict[str, Path] = {} if no_default_suite else default_sequences(cache_dir, frames)
            for path in sequences or []:
                if not path.exists():
                    raise InputError(path, "does not exist")
                runs[path.name if path.name not in runs else f"{path.parent.name}_{path.name}"] = path
            if not runs:
                raise InputError(None, "no sequences: drop --no-default-suite or add --sequence PATH")
            bench_dir = create_results_dir(output_dir, "bench")
            start_bench(bench_dir, runs, chosen, cfg, jobs or 1)
            link_latest(bench_dir)
        typer.echo(f"bench folder: {bench_dir} (resume with `flowslam bench --resume {bench_dir}`)")
        try:
            run_bench(bench_dir, progress=not no_progress, jobs=jobs, say=typer.echo)
        except BenchStopped as stopped:
            typer.echo(f"flowslam: {stopped}", err=True)
            raise typer.Exit(code=1) from None
        typer.echo((bench_dir / "table1.md").read_text())
        typer.echo(f"report in {bench_dir}; {time.perf_counter() - t0:.0f} s in all")


@app.command("flow-eval")
def flow_eval_command(
    sequence: Path = typer.Argument(..., help="A sequence with GT flow (simulated, Argoverse 2 with flow labels)."),
    frontend: str = typer.Option("ssf", "--frontend", "-f", help="Flow frontend to evaluate (ssf, gt-flow, gt)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="ssf: a weights file instead of the shipped one."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config (its dataset.* and frontend sections apply)."),
    first: Optional[int] = typer.Option(None, "--first", help="First frame index."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", "-n", help="At most N frames."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the metrics as JSON."),
    no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
):
    """Scene-flow metrics of a frontend in pipeline conditions: EPE3D, Acc, 3-way EPE, IoU."""
    with _user_errors():
        from rich.console import Console
        from rich.table import Table

        from flowslam.config import load_config
        from flowslam.flow_eval import evaluate_flow

        cfg = load_config(config, frontend=frontend, **{
            "ssf.network.weights": weights and str(weights), "dataset.first_frame": first,
            "dataset.max_frames": max_frames})
        if no_progress:
            result = evaluate_flow(sequence, cfg)
        else:
            with _progress() as bar:
                on_start, on_frame = _progress_callbacks(bar, f"flow-eval {frontend}")
                result = evaluate_flow(sequence, cfg, on_start=on_start, on_frame=on_frame)
        table = Table(title=f"scene flow of {frontend} on {sequence} ({result['pairs']} pairs)")
        table.add_column("metric")
        table.add_column(frontend, justify="right")
        table.add_column("ego-gt reference", justify="right")
        ref = result["ego-gt reference"]
        for key in ["EPE3D", "AccStrict", "AccRelax", "Outliers", "EPE_3way", "EPE_FD", "EPE_FS", "EPE_BS", "DynamicIoU"]:
            a, b = result["flow"].get(key), ref.get(key)
            table.add_row(key, "-" if a is None else f"{a:.4f}", "-" if b is None else f"{b:.4f}")
        e = result["ego_motion_error"]
        if e["trans_m_mean"] is not None:
            table.add_row("ego motion error (m / deg per step)", f"{e['trans_m_mean']:.4f} / {e['rot_deg_mean']:.4f}", "0")
        Console().print(table)
        if json_out is not None:
            from flowslam.results import write_json

            write_json(json_out, result)


@app.command("train")
def train_command(
    data: list[Path] = typer.Argument(None, help="Training sequences with GT flow and poses (simulated, AV2)."),
    val: Optional[list[Path]] = typer.Option(None, "--val", help="Held-out validation sequence (repeatable)."),
    config: Optional[Path] = typer.Option(
        None, "--config", "-c", help="Run config YAML (its training: section) or a TrainConfig YAML/JSON; options override it."),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir", "-o", help="Checkpoints and history go here."),
    preset: Optional[str] = typer.Option(None, "--preset", help="Model size: tiny (CPU) or full (GPU)."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Input frames per sample (5 default; 2 works)."),
    max_points: Optional[int] = typer.Option(None, "--max-points", help="Points sampled per frame."),
    epochs: Optional[int] = typer.Option(None, "--epochs"),
    batch_size: Optional[int] = typer.Option(None, "--batch-size"),
    lr: Optional[float] = typer.Option(None, "--lr"),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", help="Stop after this much wall time."),
    seed: Optional[int] = typer.Option(None, "--seed"),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Continue from a checkpoint."),
    init_weights: Optional[Path] = typer.Option(
        None, "--init-weights", help="Start from these weights (file or checkpoint); fresh optimiser."
    ),
    export: Optional[Path] = typer.Option(None, "--export", help="Write the best checkpoint as a weights file."),
    no_progress: bool = typer.Option(False, "--no-progress"),
):
    """Train the scene-flow network (multi-GPU/CPU: torchrun -m flowslam.sceneflow.network.train CONFIG.yaml)."""
    with _user_errors():
        from flowslam.config import load_training_config
        from flowslam.errors import InputError
        from flowslam.sceneflow.network.train import export_weights, train

        cfg = load_training_config(
            config, data=data or None, val=val or None, out_dir=out_dir, model_preset=preset, num_frames=frames,
            max_points=max_points, epochs=epochs, batch_size=batch_size, lr=lr, max_minutes=max_minutes,
            seed=seed, init_weights=init_weights,
        )
        if not cfg.data:
            raise InputError(None, "no training data: pass sequence folders (e.g. from `flowslam simulate`)")
        result = train(cfg, resume=resume, progress=not no_progress)
        last = result["history"][-1] if result["history"] else {}
        typer.echo(f"checkpoints in {result['out_dir']}; last epoch: {last}")
        if export is not None:
            digest = export_weights(Path(result["out_dir"]) / "checkpoint_best.pt", export)
            typer.echo(f"weights: {export} (sha256 {digest})")


@app.command("config")
def config_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Show this file merged over the defaults."),
):
    """Print the run configuration as YAML (the defaults, or a file merged over them)."""
    with _user_errors():
        from flowslam.config import dump_config, load_config

        typer.echo(dump_config(load_config(config)), nl=False)


@app.command("plugins")
def plugins_command():
    """List the registered frontends, backends and dataset formats."""
    from flowslam.datasets import available_formats
    from flowslam.registry import backend_names, frontend_names

    typer.echo("frontends: " + ", ".join(frontend_names()))
    typer.echo("backends:  " + ", ".join(backend_names()))
    typer.echo("datasets:  " + ", ".join(available_formats()))


if __name__ == "__main__":  # pragma: no cover
    app()
