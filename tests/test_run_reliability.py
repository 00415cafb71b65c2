"""Issue 15's cases about options, outputs and signals: no silent wrong answer, no lost
work. CLI cases run the real ``flowslam`` in a subprocess; the rest call the library."""

import json
import multiprocessing
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flowslam.config import load_config
from flowslam.errors import InputError
from flowslam.results import create_results_dir
from flowslam.run import run_sequence
from flowslam.trajectory import read_trajectory

from cli_helpers import assert_one_line_error, flowslam, write_kitti_bins


def run(seq, out, *extra):
    return flowslam("run", "--no-progress", "-o", out, *extra, seq)


@pytest.fixture
def seq(kitti_extract, tmp_path) -> Path:
    write_kitti_bins(kitti_extract, tmp_path / "seq", 5)
    return tmp_path / "seq"


@pytest.fixture
def good_run(seq, tmp_path) -> Path:
    """A finished run in tmp_path/r; returns the folder ``latest`` points at."""
    proc = run(seq, tmp_path / "r")
    assert proc.returncode == 0, proc.stderr
    return (tmp_path / "r" / "latest").resolve()


def assert_latest_unmoved(out: Path, good: Path) -> None:
    assert (out / "latest").resolve() == good
    assert sorted(p.name for p in out.iterdir() if p.name != "latest") == [good.name]


@pytest.mark.parametrize("yaml, field, problem", [
    ("kiss_icp: {max_range: -100}", "kiss_icp.max_range", "greater than 0"),
    ("kiss_icp: {max_range: .nan}", "kiss_icp.max_range", "finite"),
    ("kiss_icp: {min_range: 50, max_range: 40}", "kiss_icp", "must be below max_range"),
    ("kiss_icp: {voxel_size: -1}", "kiss_icp.voxel_size", "greater than 0"),
    ("output: {map_voxel_size: 0}", "output.map_voxel_size", "greater than 0"),
    ("output: {map_voxel_size: -0.5}", "output.map_voxel_size", "greater than 0"),
    ("isam2: {huber_k: .inf}", "isam2.huber_k", "finite"),
], ids=["negative-max-range", "nan-max-range", "min-above-max", "negative-voxel", "zero-map-voxel",
        "negative-map-voxel", "infinite-kernel"])
def test_impossible_config_values(seq, good_run, tmp_path, yaml, field, problem):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml + "\n")
    assert_one_line_error(run(seq, tmp_path / "r", "-c", cfg), str(cfg), f"'{field}'", problem)
    assert_latest_unmoved(tmp_path / "r", good_run)


@pytest.mark.parametrize("args, needles", [
    (["--variant", "a-loam", "-b", "odometry"], ["--variant a-loam", "'odometry' takes no loop closures"]),
    (["--variant", "s-loam"], ["--variant s-loam", "'odometry'"]),
    (["--weights", "w.pt"], ["--weights", "'kiss-icp' does not use it"]),
    (["-f", "ransac", "--weights", "w.pt"], ["--weights", "'ransac' does not use it"]),
], ids=["variant-odometry", "variant-default-backend", "weights-kiss-icp", "weights-ransac"])
def test_options_the_run_would_ignore(seq, good_run, tmp_path, args, needles):
    assert_one_line_error(run(seq, tmp_path / "r", *args), *needles)
    assert_latest_unmoved(tmp_path / "r", good_run)


@pytest.mark.parametrize("args, needles", [
    (["--first", "100"], ["no frames to process", "first frame 100", "has 5"]),
    (["--first", "5"], ["no frames to process", "first frame 5"]),
    (["-n", "-3"], ["'dataset.max_frames'", "greater than or equal to 1"]),
    (["-n", "0"], ["'dataset.max_frames'"]),
    (["--first", "-2"], ["'dataset.first_frame'", "greater than or equal to 0"]),
], ids=["first-beyond", "first-at-end", "negative-n", "zero-n", "negative-first"])
def test_frame_range_out_of_bounds(seq, good_run, tmp_path, args, needles):
    assert_one_line_error(run(seq, tmp_path / "r", *args), *needles)
    assert_latest_unmoved(tmp_path / "r", good_run)


def test_empty_weights_file(seq, tmp_path):
    weights = tmp_path / "empty.pt"
    weights.write_bytes(b"")
    assert_one_line_error(run(seq, tmp_path / "r", "-f", "ssf", "--weights", weights), str(weights), "is empty")
    assert not (tmp_path / "r").exists()


def test_output_folder_is_a_file(seq, tmp_path):
    out = tmp_path / "a-file"
    out.write_text("not a folder\n")
    assert_one_line_error(run(seq, out), str(out), "is a file, not a folder")
    assert_one_line_error(run(seq, out / "below"), str(out / "below"), "cannot create the results folder")
    assert out.read_text() == "not a folder\n"


def test_unwritable_output_folder(seq, tmp_path):
    if os.geteuid() == 0:  # root writes through permission bits: use a place no one can write
        out, needle = Path("/proc/flowslam-results"), "cannot create the results folder"
    else:
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        out, needle = locked / "r", "Permission denied"
    assert_one_line_error(run(seq, out), str(out), needle)


def test_eval_json_under_a_file(good_run, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("x\n")
    est = good_run / "trajectory_tum.txt"
    proc = flowslam("eval", "--json", blocker / "m.json", est, est)
    assert_one_line_error(proc, str(blocker / "m.json"), "cannot write")
    assert "APE" in proc.stdout  # the table was printed before the write failed


def test_output_file_size_limit_keeps_what_was_written(seq, good_run, tmp_path):
    """A real OS-level write failure (RLIMIT_FSIZE, with SIGXFSZ ignored so writes fail
    with EFBIG): one line naming the file, exit 2, files before it kept, latest unmoved."""
    # every other file of the run fits (config.yaml, with its comments, is the largest:
    # ~65 kB), the static map does not
    others = [p.stat().st_size for p in good_run.iterdir() if not p.name.startswith(("static_map", "dynamic_points"))]
    limit = max(others) + 4096
    assert (good_run / "static_map.ply").stat().st_size > limit

    def limit_file_size():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = dict(os.environ, COLUMNS="240", NO_COLOR="1")
    proc = subprocess.run([sys.executable, "-m", "flowslam", "run", "--no-progress", "-o", tmp_path / "r", seq],
                          capture_output=True, text=True, env=env, timeout=300, preexec_fn=limit_file_size)
    assert_one_line_error(proc, "static_map.ply", "cannot write", "too large")
    new = [p for p in (tmp_path / "r").iterdir() if p.name not in ("latest", good_run.name)]
    assert len(new) == 1
    assert len(read_trajectory(new[0] / "trajectory_tum.txt")) == 5
    assert not (new[0] / "run.json").exists() and not list(new[0].glob(".tmp-*"))
    assert (tmp_path / "r" / "latest").resolve() == good_run


def test_disk_full_names_the_file_and_keeps_the_rest(seq, tmp_path, monkeypatch):
    import errno

    import flowslam.results as results

    def no_space(path, traj):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(results, "write_kitti", no_space)
    cfg = load_config(output_dir=str(tmp_path / "r"))
    with pytest.raises(InputError) as err:
        run_sequence(seq, cfg)
    assert "trajectory_kitti.txt" in str(err.value) and "No space left on device" in str(err.value)
    (run_dir,) = (tmp_path / "r").iterdir()  # no 'latest': the folder never got its run.json
    assert len(read_trajectory(run_dir / "trajectory_tum.txt")) == 5
    assert not (run_dir / "trajectory_kitti.txt").exists() and not list(run_dir.glob(".tmp-*"))


def test_sigterm_keeps_the_partial_run(kitti_extract, tmp_path):
    out = tmp_path / "r"
    env = dict(os.environ, COLUMNS="240", NO_COLOR="1", PYTHONFAULTHANDLER="1")  # a crash prints every thread's stack
    proc = subprocess.Popen(
        [sys.executable, "-m", "flowslam", "run", "--no-progress", "-f", "ssf", "-o", out, kitti_extract],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 240
    while not (out.exists() and any(out.iterdir())):  # the folder appears when the first scan is read
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.1)
    time.sleep(2.0)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    print(stderr)  # whole, in the report of a failure (an assertion message is cut short)
    assert proc.returncode == 128 + signal.SIGTERM, (proc.returncode, stderr)
    assert "Traceback" not in stderr and "flowslam: stopped by SIGTERM" in stderr
    latest = out / "latest"
    info = json.loads((latest / "run.json").read_text())
    assert info["complete"] is False and info["error"] == "stopped by SIGTERM"
    assert 0 < info["frames_processed"] < 16, info
    assert len(read_trajectory(latest / "trajectory_tum.txt")) == info["frames_processed"]
    assert (latest / "static_map.ply").is_file()


def test_a_signal_while_writing_waits_for_run_json(seq, tmp_path, monkeypatch):
    """SIGINT arriving in the middle of the writes: every file, run.json last, then the
    KeyboardInterrupt."""
    from flowslam.mapping import StaticMapBuilder

    real_write = StaticMapBuilder.write

    def write_after_ctrl_c(self, path, *args):
        os.kill(os.getpid(), signal.SIGINT)
        return real_write(self, path, *args)

    monkeypatch.setattr(StaticMapBuilder, "write", write_after_ctrl_c)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # background jobs start with SIGINT ignored
    cfg = load_config(output_dir=str(tmp_path / "r"))
    try:
        with pytest.raises(KeyboardInterrupt):
            run_sequence(seq, cfg)
    finally:
        signal.signal(signal.SIGINT, previous)
    latest = tmp_path / "r" / "latest"
    info = json.loads((latest / "run.json").read_text())
    assert info["complete"] is True and info["frames_processed"] == 5
    assert (latest / "static_map.ply").stat().st_size > 0


def test_a_signal_that_surfaces_as_another_error_stops_the_run_as_that_signal(seq, tmp_path, monkeypatch):
    """SIGTERM whose handler raised inside compiled code that then returned anyway (numba's
    dispatcher did so in CI: ``SystemError: ... returned a result with an exception set``,
    caused by ``Terminated``): the run stops as stopped by SIGTERM, with the frames before it."""
    from flowslam.frontends.kiss_icp import KissIcpFrontend
    from flowslam.signals import Terminated

    real_process, calls = KissIcpFrontend.process, []

    def process_until_the_third(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            try:
                raise Terminated(signal.SIGTERM)
            except Terminated as stop:
                raise SystemError("CPUDispatcher(<function f>) returned a result with an exception set") from stop
        return real_process(self, *args, **kwargs)

    monkeypatch.setattr(KissIcpFrontend, "process", process_until_the_third)
    outcome = run_sequence(seq, load_config(frontend="kiss-icp", output_dir=str(tmp_path / "r")))
    assert isinstance(outcome.result.error, Terminated) and outcome.result.failed_index == 2
    info = json.loads((tmp_path / "r" / "latest" / "run.json").read_text())
    assert info["error"] == "stopped by SIGTERM" and info["frames_processed"] == 2


def test_an_error_without_a_signal_behind_it_stays_that_error():
    from flowslam.signals import stop_behind

    try:
        try:
            raise ValueError("first")
        except ValueError as first:
            raise RuntimeError("second") from first
    except RuntimeError as error:
        assert stop_behind(error) is error


def test_stopped_at_the_first_frame_says_nothing_was_kept(kitti_extract, tmp_path):
    scans = write_kitti_bins(kitti_extract, tmp_path / "seq", 3)
    scans[0].write_bytes(scans[0].read_bytes()[:-5])
    proc = run(tmp_path / "seq", tmp_path / "r")
    assert_one_line_error(proc, str(scans[0]), "multiple of 16")
    assert "no frame was processed" in proc.stdout and "frames before it is written" not in proc.stdout
    info = json.loads((tmp_path / "r" / "latest" / "run.json").read_text())
    assert info["frames_processed"] == 0 and info["failed_index"] == 0 and info["complete"] is False
    assert not (tmp_path / "r" / "latest" / "trajectory_tum.txt").exists()


def _create_at(barrier, output_dir, queue):
    barrier.wait()
    try:
        queue.put(str(create_results_dir(output_dir, "race")))
    except BaseException as e:  # noqa: BLE001 - reported to the parent
        queue.put(f"error: {e!r}")


def test_results_folder_creation_is_race_free(tmp_path):
    ctx = multiprocessing.get_context("fork")
    for round_ in range(5):
        n, out = 6, tmp_path / f"round{round_}"
        barrier, queue = ctx.Barrier(n), ctx.Queue()
        procs = [ctx.Process(target=_create_at, args=(barrier, out, queue)) for _ in range(n)]
        for p in procs:
            p.start()
        made = [queue.get(timeout=60) for _ in procs]
        for p in procs:
            p.join()
        assert not [m for m in made if m.startswith("error")], made
        assert len(set(made)) == n and all(Path(m).is_dir() for m in made)


def test_signals_held_while_writing_are_delivered_after():
    from flowslam.signals import Terminated, deferred_signals, terminate_as_interrupt

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), terminate_as_interrupt():
        with deferred_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            reached = True
    assert reached
    assert signal.getsignal(signal.SIGTERM) == before


def test_simulate_into_an_impossible_folder(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("x\n")
    proc = flowslam("simulate", blocker / "seq", "-n", "2", "--no-progress")
    assert_one_line_error(proc, str(blocker / "seq"), "Not a directory")
    assert_one_line_error(flowslam("simulate", blocker, "-n", "2", "--no-progress"), str(blocker), "not a folder")


def test_weights_are_taken_by_the_frontends_with_a_network(seq, tmp_path):
    from flowslam.run import check_requested_options
    from flowslam.registry import make_backend, make_frontend

    for name in ["ssf", "sf", "gt-seg", "gt-flow+ssf-seg"]:
        cfg = load_config(frontend=name)
        check_requested_options(cfg, make_frontend(name, cfg), make_backend("odometry", cfg), ["ssf.network.weights"])
    cfg = load_config(frontend="gt")
    with pytest.raises(InputError, match="'gt' does not use it .it reads flow_odometry"):
        check_requested_options(cfg, make_frontend("gt", cfg), make_backend("odometry", cfg), ["ssf.network.weights"])


def test_ctrl_c_in_the_progress_callback_keeps_the_scans_processed(seq, tmp_path):
    """Ctrl-C handled between two scans (here in ``on_frame``, the progress bar's callback)
    stops the run like one inside a scan: the folder holds the scans done, and the scan
    said to have stopped it is the first one not processed."""
    def ctrl_c_after_the_second(k, seconds):
        if k == 1:
            raise KeyboardInterrupt

    cfg = load_config(output_dir=str(tmp_path / "r"))
    outcome = run_sequence(seq, cfg, on_frame=ctrl_c_after_the_second)
    assert isinstance(outcome.result.error, KeyboardInterrupt) and outcome.result.failed_index == 2
    info = json.loads((tmp_path / "r" / "latest" / "run.json").read_text())
    assert info["complete"] is False and info["frames_processed"] == 2 and info["failed_index"] == 2
    assert len(read_trajectory(tmp_path / "r" / "latest" / "trajectory_tum.txt")) == 2


def test_sigterm_during_a_scan_stops_the_run_once_that_scan_is_done(seq, tmp_path, monkeypatch):
    """Under ``terminate_as_interrupt`` (``flowslam run``), SIGTERM arriving inside the
    frontend does not raise there: the scan in progress finishes, and the run stops before
    the next one, which is the scan said to have stopped it."""
    from flowslam.frontends.kiss_icp import KissIcpFrontend
    from flowslam.signals import Terminated, terminate_as_interrupt

    real_process, calls = KissIcpFrontend.process, []

    def sigterm_inside_the_third(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler has run by now, in the middle of this scan
        return real_process(self, *args, **kwargs)

    monkeypatch.setattr(KissIcpFrontend, "process", sigterm_inside_the_third)
    with terminate_as_interrupt():
        outcome = run_sequence(seq, load_config(frontend="kiss-icp", output_dir=str(tmp_path / "r")))
    assert isinstance(outcome.result.error, Terminated) and outcome.result.failed_index == 3
    info = json.loads((tmp_path / "r" / "latest" / "run.json").read_text())
    assert info["error"] == "stopped by SIGTERM" and info["frames_processed"] == 3 and len(calls) == 3


def test_sigterm_at_safe_points_only_under_terminate_as_interrupt():
    from flowslam.signals import Terminated, sigterm_at_safe_points, terminate_as_interrupt

    before = signal.getsignal(signal.SIGTERM)
    with sigterm_at_safe_points() as check:  # another handler in place: nothing changes
        assert signal.getsignal(signal.SIGTERM) == before
        check()
    with terminate_as_interrupt():
        with sigterm_at_safe_points() as check:
            check()  # nothing recorded
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            reached = True  # not raised where it landed ...
            with pytest.raises(Terminated):
                check()  # ... but here
            check()  # once
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            with pytest.raises(Terminated):  # a second one before check(): at once
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
        # recorded and not raised before the block ends: sent again, to terminate_as_interrupt's handler
        with pytest.raises(Terminated):
            with sigterm_at_safe_points():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
    assert reached and signal.getsignal(signal.SIGTERM) == before
