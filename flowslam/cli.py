"""The ``flowslam`` command line (typer). Heavy modules are imported inside commands.

Bad input (``InputError``) prints one line, ``flowslam: error: FILE: problem``, and
exits with code 2; ``--debug`` shows the traceback instead. So does a bad command
line (an unknown option, a value that is not one of the choices).

Options are ``Annotated[type, typer.Option(...)]``; closed sets are ``str`` enums, so
``--help`` lists the choices. Frontends and backends stay free strings (plug-ins), their
help lists the names registered when the command starts.
"""

from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer


class _Flowslam(typer.Typer):
    """``typer.Typer`` whose command-line errors are one ``flowslam: error:`` line, exit 2."""

    def __call__(self, *args, **kwargs):
        try:  # typer >= 0.2x ships its own copy of click
            from typer._click import exceptions as click_errors
        except ImportError:  # pragma: no cover
            from click import exceptions as click_errors

        try:
            code = super().__call__(*args, **kwargs, standalone_mode=False)
        except getattr(click_errors, "NoArgsIsHelpError", ()) as error:  # the help is already shown
            sys.exit(error.exit_code)
        except click_errors.UsageError as error:
            where = f" (see `{error.ctx.command_path} --help`)" if error.ctx is not None else ""
            print(f"flowslam: error: {' '.join(error.format_message().split())}{where}", file=sys.stderr)
            sys.exit(2)
        except click_errors.ClickException as error:
            error.show()
            sys.exit(error.exit_code)
        except (getattr(click_errors, "Abort", ()) or typer.Abort):  # typer 0.29 moved it out of its click copy
            print("Aborted!", file=sys.stderr)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)


app = _Flowslam(
    name="flowslam",
    help="LiDAR SLAM with scene flow as odometry, on a GTSAM factor graph.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)

_state = {"debug": False}


# -- closed sets (str enums: --help lists them; tests/test_cli_idioms.py checks each
#    against its source, which is too heavy to import at start-up) -----------------------

class Variant(str, Enum):
    """``--variant`` (``flowslam.config.VARIANTS``)."""

    a_loam = "a-loam"
    s_loam = "s-loam"


class Preset(str, Enum):
    """``simulate --preset`` (``flowslam.simulation.preset_names()``)."""

    static = "static"
    dh = "dh"
    dt = "dt"
    rush_hour = "rush-hour"
    kitti00_path = "kitti00-path"
    demo = "demo"


class Sensor(str, Enum):
    """``simulate --sensor`` (``flowslam.simulation.sensor_names()``)."""

    hdl64 = "hdl64"
    av2 = "av2"
    vlp32c = "vlp32c"
    vlp16 = "vlp16"
    os1_128 = "os1-128"


class ModelPreset(str, Enum):
    """``train --preset``: the network size (``flowslam.sceneflow.network.model.PRESETS``)."""

    tiny = "tiny"
    full = "full"
    cpu = "cpu"


def _names(kind: str) -> list[str]:
    """The plug-ins of ``kind`` installed now (entry points; nothing is imported)."""
    from flowslam.registry import plugins

    return [p.name for p in plugins(kind)]


DatasetFormat = Enum("DatasetFormat", {name: name for name in _names("dataset")}, type=str)
"""``--format``: every reader installed (built-ins and ``flowslam.datasets`` plug-ins)."""


def _value(choice: Optional[Enum]) -> Optional[str]:
    return None if choice is None else choice.value


# -- options shared by several commands ------------------------------------------------

NoProgress = Annotated[bool, typer.Option("--no-progress", help="Hide the progress bar(s).")]
ConfigFile = Annotated[Optional[Path], typer.Option(
    "--config", "-c", help="Run config YAML (`flowslam config` prints one); options override it.")]
Weights = Annotated[Optional[Path], typer.Option(
    "--weights", help="ssf: a weights file instead of the shipped one.")]
First = Annotated[Optional[int], typer.Option("--first", help="First frame index.")]
MaxFrames = Annotated[Optional[int], typer.Option("--max-frames", "-n", help="Process at most N frames.")]
FRONTENDS_HELP = f"Registered: {', '.join(_names('frontend'))} (`flowslam plugins`)."
BACKENDS_HELP = f"Registered: {', '.join(_names('backend'))} (`flowslam plugins`)."


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks and debug logs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only warnings and errors.")] = False,
):
    _state["debug"] = debug
    from flowslam.threads import set_thread_defaults

    set_thread_defaults()  # before numpy, torch and Open3D load (passive OpenMP, one OpenBLAS thread)
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
    sequence: Annotated[Path, typer.Argument(help="Sequence: KITTI folder, scan folder, ROS bag, AV2 log.")],
    frontend: Annotated[Optional[str], typer.Option(
        "--frontend", "-f",
        help="Frontend (default kiss-icp): kiss-icp, ransac, ssf, sf (learned flow, no segmentation); ablations that "
             "read ground truth, SSF-PAN markers: gt (GT flow + GT segmentation), gt-flow (GT flow, none), "
             "gt-seg (◐ ssf's flow + GT segmentation), gt-flow+ssf-seg (○ GT flow + ssf's segmentation). "
             + FRONTENDS_HELP)] = None,
    backend: Annotated[Optional[str], typer.Option(
        "--backend", "-b", help="Backend (default odometry). " + BACKENDS_HELP)] = None,
    variant: Annotated[Optional[Variant], typer.Option(
        "--variant", help="a-loam (odometry only) or s-loam (loop closure, default; backends that take loops).")] = None,
    mapping: Annotated[Optional[bool], typer.Option(
        "--mapping/--no-mapping", help="Scan-to-map factors beside the odometry (LOAM's mapping stage; "
                                       "graph backends: -b isam2). Default: the config's mapping.enabled.")] = None,
    config: ConfigFile = None,
    output_dir: Annotated[Optional[Path], typer.Option(
        "--output-dir", "-o", help="Where run folders go (default results/).")] = None,
    fmt: Annotated[Optional[DatasetFormat], typer.Option(
        "--format", help="Force the reader (default: guessed from the path).")] = None,
    topic: Annotated[Optional[str], typer.Option("--topic", help="ROS bags: the PointCloud2 topic.")] = None,
    gt_topic: Annotated[Optional[str], typer.Option("--gt-topic", help="ROS bags: Odometry/PoseStamped GT topic.")] = None,
    sequence_id: Annotated[Optional[str], typer.Option("--sequence", help="KITTI sequence id (e.g. 00).")] = None,
    poses: Annotated[Optional[Path], typer.Option("--poses", help="Scan folders: GT poses file (KITTI or TUM).")] = None,
    weights: Weights = None,
    kitti_correction: Annotated[Optional[float], typer.Option(
        "--kitti-correction-deg", help="KITTI beam elevation correction (default 0.205; 0 = off).")] = None,
    first: First = None,
    max_frames: MaxFrames = None,
    fix_times: Annotated[bool, typer.Option(
        "--fix-times", help="Repair scan timestamps that do not increase strictly (logged) instead of stopping.")] = False,
    no_progress: NoProgress = False,
    rerun: Annotated[Optional[Path], typer.Option(
        "--rerun", help="Also record a 3-D view of the run into this .rrd file (rerun; pip install flowslam[viz]).")] = None,
):
    """Estimate the trajectory of SEQUENCE and write it (TUM, KITTI), metrics and a plot."""
    from flowslam.signals import terminate_as_interrupt

    with _user_errors(), _stopped_by_signal(), terminate_as_interrupt():
        from flowslam.config import load_config

        overrides = {
            "ssf.network.weights": weights and str(weights),
            "dataset.format": _value(fmt), "dataset.topic": topic, "dataset.gt_topic": gt_topic,
            "dataset.sequence": sequence_id, "dataset.poses": poses and str(poses),
            "dataset.kitti_vertical_correction_deg": kitti_correction,
            "dataset.first_frame": first, "dataset.max_frames": max_frames,
            "dataset.fix_times": fix_times or None,
            "mapping.enabled": mapping,
        }
        cfg = load_config(
            config, frontend=frontend, backend=backend, output_dir=output_dir and str(output_dir),
            variant=_value(variant), **overrides,
        )
        requested = [key for key, value in overrides.items() if value is not None]
        if variant is not None:
            requested.append("loop_closure.enabled")
        from flowslam.run import run_sequence

        live = None
        if rerun is not None:
            from flowslam.viz.live import LiveRecorder

            live = LiveRecorder(rerun)
        listeners = [live.on_step] if live is not None else []
        if no_progress:
            outcome = run_sequence(sequence, cfg, requested=requested, step_listeners=listeners)
        else:
            with _progress() as bar:
                on_start, on_frame = _progress_callbacks(bar, cfg.frontend)
                outcome = run_sequence(sequence, cfg, on_start=on_start, on_frame=on_frame, requested=requested,
                                       step_listeners=listeners)
        _report_run(outcome)
        if live is not None:
            typer.echo(f"3-D view: {live.finish(outcome.result.poses, outcome.run_dir)} (open it with `rerun FILE`)")
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
    estimate: Annotated[Path, typer.Argument(help="Estimated trajectory (TUM or KITTI file).")],
    ground_truth: Annotated[Path, typer.Argument(help="Ground-truth trajectory (TUM or KITTI file).")],
    max_diff: Annotated[float, typer.Option(
        "--max-diff", help="Max timestamp difference (s) for association.")] = 0.01,
    offset: Annotated[float, typer.Option("--offset", help="Seconds added to the estimate's timestamps.")] = 0.0,
    delta: Annotated[list[str], typer.Option(
        "--delta", help="RPE deltas: N (frames) or Nm (metres); repeatable.")] = ["1"],  # noqa: B006 (typer copies it)
    no_align: Annotated[bool, typer.Option("--no-align", help="APE without Umeyama SE(3) alignment.")] = False,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Also write the metrics as JSON.")] = None,
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
    out_dir: Annotated[Path, typer.Argument(help="Output folder (KITTI layout + GT + manifest.json).")],
    preset: Annotated[Preset, typer.Option("--preset", "-p", help="The scenario.")] = Preset.dt,
    frames: Annotated[Optional[int], typer.Option(
        "--frames", "-n", help="Number of scans (default: the preset's).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Town, traffic and noise seed (same seed = same output).")] = 0,
    sensor: Annotated[Optional[Sensor], typer.Option(
        "--sensor", "-s", help="LiDAR model (default: the preset's).")] = None,
    columns: Annotated[Optional[int], typer.Option("--columns", help="Azimuth steps per revolution.")] = None,
    max_range: Annotated[Optional[float], typer.Option("--max-range", help="Maximum range (m).")] = None,
    noise: Annotated[Optional[float], typer.Option("--noise", help="Range noise, 1 sigma (m).")] = None,
    dropout: Annotated[Optional[float], typer.Option("--dropout", help="Share of returns dropped at random.")] = None,
    distortion: Annotated[bool, typer.Option(
        "--distortion/--no-distortion", help="Motion during the sweep.")] = False,
    trajectory: Annotated[Optional[Path], typer.Option(
        "--trajectory", help="Drive along this KITTI/TUM trajectory.")] = None,
    trajectory_times: Annotated[Optional[Path], typer.Option(
        "--trajectory-times", help="times.txt for --trajectory.")] = None,
    first_pose: Annotated[int, typer.Option("--first-pose", help="Start at this pose of --trajectory.")] = 0,
    preview: Annotated[bool, typer.Option("--preview", help="Write preview.png (top view by class and flow).")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing output folder.")] = False,
    workers: Annotated[Optional[int], typer.Option("--workers", help="Rendering processes (default: cores).")] = None,
    no_progress: NoProgress = False,
):
    """Simulate a LiDAR sequence with exact GT poses, scene flow, classes and instances."""
    with _user_errors():
        from flowslam.simulation import simulate, write_preview

        kwargs = dict(
            preset=preset.value, frames=frames, seed=seed, sensor=_value(sensor), columns=columns,
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
    cache_dir: Annotated[Optional[Path], typer.Option("--cache-dir", help="Where the demo sequence is cached.")] = None,
    refresh: Annotated[bool, typer.Option("--refresh", help="Simulate the demo sequence again.")] = False,
    output_dir: Annotated[Path, typer.Option("--output-dir", "-o", help="Where run folders go.")] = Path("results"),
    frontends: Annotated[Optional[list[str]], typer.Option(
        "--frontend", "-f", help="These frontends (repeatable; default kiss-icp, ssf, gt, gt-flow). " + FRONTENDS_HELP,
    )] = None,
    no_progress: NoProgress = False,
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
    sequences: Annotated[Optional[list[Path]], typer.Option(
        "--sequence", "-s", help="Also run on this sequence (repeatable; any format `run` reads).")] = None,
    frontends: Annotated[Optional[list[str]], typer.Option(
        "--frontend", "-f", help="Only these frontends (repeatable; default: every baseline and ablation). "
        + FRONTENDS_HELP)] = None,
    no_default_suite: Annotated[bool, typer.Option("--no-default-suite", help="Only the --sequence ones.")] = False,
    frames: Annotated[Optional[int], typer.Option(
        "--frames", help="Shorten the default suite's sequences (quick look).")] = None,
    config: Annotated[Optional[Path], typer.Option(
        "--config", "-c", help="Run config YAML applied to every run (`flowslam config` prints one).")] = None,
    output_dir: Annotated[Path, typer.Option("--output-dir", "-o", help="Where the bench folder goes.")] = Path("results"),
    resume: Annotated[Optional[Path], typer.Option(
        "--resume", help="Go on with the unfinished bench in this folder.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(
        "--cache-dir", help="Where simulated sequences are cached.")] = None,
    jobs: Annotated[Optional[int], typer.Option(
        "--jobs", "-j", min=1, help="Cells run at once, one OpenMP thread each when > 1 (default 1).")] = None,
    no_progress: NoProgress = False,
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
    sequence: Annotated[Path, typer.Argument(help="A sequence with GT flow (simulated, Argoverse 2 with flow labels).")],
    frontend: Annotated[str, typer.Option(
        "--frontend", "-f", help="Flow frontend to evaluate (ssf, gt-flow, gt). " + FRONTENDS_HELP)] = "ssf",
    weights: Weights = None,
    config: Annotated[Optional[Path], typer.Option(
        "--config", "-c", help="Run config YAML (its dataset.* and frontend sections apply).")] = None,
    first: First = None,
    max_frames: MaxFrames = None,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Also write the metrics as JSON.")] = None,
    skip_pairs: Annotated[int, typer.Option(
        "--skip-pairs", help="Run every frame but score only the pairs after the first N (a warm-up).")] = 0,
    no_progress: NoProgress = False,
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
            result = evaluate_flow(sequence, cfg, skip_pairs=skip_pairs)
        else:
            with _progress() as bar:
                on_start, on_frame = _progress_callbacks(bar, f"flow-eval {frontend}")
                result = evaluate_flow(sequence, cfg, on_start=on_start, on_frame=on_frame, skip_pairs=skip_pairs)
        skipped = f", the first {skip_pairs} not scored" if skip_pairs else ""
        table = Table(title=f"scene flow of {frontend} on {sequence} ({result['pairs']} pairs{skipped})")
        table.add_column("metric")
        table.add_column(frontend, justify="right")
        table.add_column("ego-gt reference", justify="right")
        ref = result["ego-gt reference"]
        for key in ["EPE3D", "AccStrict", "AccRelax", "Outliers", "EPE_3way", "EPE_FD", "EPE_FS", "EPE_BS", "DynamicIoU", "SSA"]:
            a, b = result["flow"].get(key), ref.get(key)
            table.add_row(key, "-" if a is None else f"{a:.4f}", "-" if b is None else f"{b:.4f}")
        e = result["ego_motion_error"]
        if e["trans_m_mean"] is not None:
            table.add_row("ego motion error (m / deg per step)", f"{e['trans_m_mean']:.4f} / {e['rot_deg_mean']:.4f}", "0")
        for label, name in (("objects", "objects"), ("objects in the flow region", "objects_in_region")):
            objects = result.get(name)
            if objects is None:  # the GT has no instances or the frontend gives none
                continue
            for key in ("recall", "precision", "median_speed_error_mps", "median_velocity_error_mps",
                        "id_switches_per_100_pairs"):
                value = objects[key]
                table.add_row(f"{label}: {key}", "-" if value is None else f"{value:.4f}", "")
            table.add_row(f"{label}: GT / predicted / found", f"{objects['gt_objects']} / "
                          f"{objects['predicted_objects']} / {objects['found']}", "")
            table.add_row(f"{label}: missed unflagged / split / merged", f"{objects['missed_unflagged']} / "
                          f"{objects['missed_split']} / {objects['missed_merged']}", "")
        Console().print(table)
        if json_out is not None:
            from flowslam.results import write_json

            write_json(json_out, result)


@app.command("train")
def train_command(
    data: Annotated[Optional[list[Path]], typer.Argument(
        help="Training sequences with GT flow and poses (simulated, AV2).")] = None,
    val: Annotated[Optional[list[Path]], typer.Option(
        "--val", help="Held-out validation sequence (repeatable).")] = None,
    config: Annotated[Optional[Path], typer.Option(
        "--config", "-c", help="Run config YAML, the one `run` reads (`flowslam config` prints it): its training: "
        "section applies; options override it.")] = None,
    out_dir: Annotated[Optional[Path], typer.Option("--out-dir", "-o", help="Checkpoints and history go here.")] = None,
    preset: Annotated[Optional[ModelPreset], typer.Option(
        "--preset", help="Model size: tiny (CPU; cpu is the same) or full (GPU).")] = None,
    frames: Annotated[Optional[int], typer.Option(
        "--frames", help="Input frames per sample (5 default; 2 works).")] = None,
    max_points: Annotated[Optional[int], typer.Option("--max-points", help="Points sampled per frame.")] = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Length of the OneCycle schedule.")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Samples per optimiser step.")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Peak learning rate.")] = None,
    max_minutes: Annotated[Optional[float], typer.Option(
        "--max-minutes", help="Stop after this much wall time.")] = None,
    seed: Annotated[Optional[int], typer.Option("--seed", help="Sampling, priors and initialisation seed.")] = None,
    resume: Annotated[Optional[Path], typer.Option("--resume", help="Continue from a checkpoint.")] = None,
    init_weights: Annotated[Optional[Path], typer.Option(
        "--init-weights", help="Start from these weights (file or checkpoint); fresh optimiser.")] = None,
    export: Annotated[Optional[Path], typer.Option(
        "--export", help="Write the best checkpoint as a weights file.")] = None,
    no_progress: NoProgress = False,
):
    """Train the scene-flow network (multi-GPU/CPU: torchrun -m flowslam.sceneflow.network.train CONFIG.yaml)."""
    with _user_errors():
        from flowslam.config import load_training_config
        from flowslam.errors import InputError
        from flowslam.sceneflow.network.train import export_weights, train

        cfg = load_training_config(
            config, data=data or None, val=val or None, out_dir=out_dir, model_preset=_value(preset), num_frames=frames,
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


@app.command("adapt")
def adapt_command(
    sequences: Annotated[list[Path], typer.Argument(
        help="Unlabelled sequences, in any format `run` reads (their GT, if any, is used only in the report).")],
    weights_out: Annotated[Path, typer.Option(
        "--weights-out", help="Write the adapted weights here (+ FILE.sha256); `run --weights FILE` uses them.")],
    weights: Weights = None,
    config: Annotated[Optional[Path], typer.Option(
        "--config", "-c", help="Run config YAML: its ssf: section makes the teacher, its adapt: section the run.")] = None,
    out_dir: Annotated[Optional[Path], typer.Option(
        "--out-dir", "-o", help="Teacher cache, checkpoints and report (default runs/adapt).")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option(
        "--cache-dir", help="Teacher cache shared between adapt runs (default OUT_DIR/cache).")] = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Passes over the training pairs.")] = None,
    holdout: Annotated[Optional[float], typer.Option(
        "--holdout", help="Fraction of each sequence's last frames never trained on (0.2 default).")] = None,
    max_minutes: Annotated[Optional[float], typer.Option(
        "--max-minutes", help="Stop after this much wall time (teacher included).")] = None,
    first: First = None,
    max_frames: MaxFrames = None,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue from OUT_DIR/checkpoint_last.pt (same weights and sequences).")] = False,
    no_progress: NoProgress = False,
):
    """Fine-tune the scene-flow network on your own unlabelled sequences (self-supervised, CPU by default)."""
    with _user_errors():
        from rich.console import Console

        from flowslam.config import load_config
        from flowslam.sceneflow.adapt import adapt

        cfg = load_config(config, **{
            "ssf.network.weights": weights and str(weights), "dataset.first_frame": first,
            "dataset.max_frames": max_frames, "adapt.out_dir": out_dir and str(out_dir),
            "adapt.cache_dir": cache_dir and str(cache_dir), "adapt.epochs": epochs,
            "adapt.holdout_fraction": holdout, "adapt.max_minutes": max_minutes})
        result = adapt(sequences, cfg, weights_out, resume=resume, progress=not no_progress)
        title = (f"on the held-out frames (weights of epoch {result['written_epoch']}, best held-out score at "
                 f"epoch {result['best_epoch']}; {result['minutes']:.1f} min)")
        for mode, suffix in (("network-only ssf", ""), ("default ssf (refined, objects)", "_refined")):
            rows = [(seq, both[f"start{suffix}"], both[f"adapted{suffix}"]) for seq, both in result["report"].items()
                    if f"start{suffix}" in both]
            if rows:
                Console().print(_comparison_table(f"{mode} {title}", rows))
        typer.echo(f"weights: {result['weights']} (sha256 {result['sha256']}); "
                   f"report: {Path(cfg.adapt.out_dir) / 'report.json'}")


def _comparison_table(title: str, rows: list[tuple[str, dict, dict]]):
    """A rich table of (sequence, starting weights' scores, adapted weights' scores) rows."""
    from rich.table import Table

    table = Table(title=title)
    for column in ("sequence", "measure", "starting weights", "adapted"):
        table.add_column(column, justify="left" if column in ("sequence", "measure") else "right")
    flat = lambda d: {**{k: v for k, v in d.items() if k != "gt_flow"},  # noqa: E731
                      **{f"GT {k}": v for k, v in d.get("gt_flow", {}).items()}}
    for seq, start, adapted in rows:
        start, adapted = flat(start), flat(adapted)
        for key in start:
            table.add_row(Path(seq).name, key, f"{start[key]:.4f}", f"{adapted.get(key, float('nan')):.4f}")
    return table


@app.command("view")
def view_command(
    results: Annotated[Path, typer.Argument(help="A results folder of `flowslam run` (e.g. results/latest).")],
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="The .rrd file to write (default RESULTS/view.rrd).")] = None,
    no_scans: Annotated[bool, typer.Option(
        "--no-scans", help="Do not re-read the scans from the run's dataset (trajectories, maps, objects only).")] = False,
):
    """Build a 3-D view (rerun .rrd) of a results folder after the fact (pip install flowslam[viz])."""
    with _user_errors():
        from flowslam.viz import import_rerun

        import_rerun()  # before any work: one line saying how to install it
        from flowslam.viz.from_results import record_results

        path = record_results(results, out or results / "view.rrd", scans=not no_scans)
        typer.echo(f"3-D view: {path} (open it with `rerun {path}`)")


@app.command("config")
def config_command(
    config: Annotated[Optional[Path], typer.Option(
        "--config", "-c", help="Show this file merged over the defaults.")] = None,
):
    """Print the run configuration as YAML (the defaults, or a file merged over them)."""
    with _user_errors():
        from flowslam.config import dump_config, load_config

        typer.echo(dump_config(load_config(config)), nl=False)


@app.command("plugins")
def plugins_command():
    """List the frontends, backends and dataset formats with the package of each."""
    from flowslam.registry import ignored_plugins, plugins

    for kind in ("frontend", "backend", "dataset"):
        found = plugins(kind)
        typer.echo(f"{kind}s:")
        width = max((len(p.name) for p in found), default=0)
        for p in found:
            mark = "" if p.builtin else "  [third-party]"
            typer.echo(f"  {p.name:<{width}}  {p.package}{mark}  ({p.target})")
        for p in ignored_plugins(kind):
            typer.echo(f"  ignored: {p.name!r} of {p.package} ({p.target}): the name is taken", err=True)


if __name__ == "__main__":  # pragma: no cover
    app()
