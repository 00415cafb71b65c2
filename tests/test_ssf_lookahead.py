"""``ssf.lookahead``: the stages before flow-to-pose of pair (k, k+1) run in a background
thread while pair (k-1, k) finishes (objects, backend). Real KITTI scans, real torch /
Open3D / GTSAM, through the run loop (``flowslam.pipeline.drive``, which reads one scan
ahead and hands it to the frontend's ``upcoming``)."""

import threading

import numpy as np
import pytest

from flowslam.config import PipelineConfig
from flowslam.datasets import open_dataset
from flowslam.errors import InputError
from flowslam.pipeline import run_pipeline
from flowslam.registry import make_backend, make_frontend

FRAMES = range(6)


def _run(kitti_extract, ssf: dict, lookahead: bool, frontend: str = "ssf"):
    """The ``RunResult`` of ``frontend`` + isam2 a-loam and its frontend outputs."""
    config = PipelineConfig(frontend=frontend, backend="isam2", ssf={**ssf, "lookahead": lookahead})
    outputs = []  # no loop closer: a-loam
    result = run_pipeline(open_dataset(kitti_extract), make_frontend(frontend, config), make_backend("isam2", config),
                          FRAMES, on_output=lambda frame, out: outputs.append(out))
    return result, outputs


def _ran_ahead(result) -> list[bool]:
    return ["ahead_wait_ms" in stats for stats in result.frontend_stats[1:]]


@pytest.mark.usefixtures("one_torch_thread")
def test_network_only_chain_is_bit_identical_with_lookahead(kitti_extract):
    """No Open3D in the chain (network + flow-to-pose): every number must be equal."""
    options = {"refine": {"enabled": False}}
    (seq, seq_out), (ahead, ahead_out) = (_run(kitti_extract, options, flag) for flag in (False, True))
    assert seq.error is None and ahead.error is None
    assert np.array_equal(np.array(seq.odometry), np.array(ahead.odometry))
    for a, b in zip(seq_out[1:], ahead_out[1:]):
        assert np.array_equal(a.flow, b.flow) and np.array_equal(a.static_mask, b.static_mask)
    assert all(_ran_ahead(ahead)) and not any(_ran_ahead(seq))


@pytest.mark.usefixtures("one_torch_thread")
def test_full_chain_with_lookahead_equals_the_sequential_run(kitti_extract):
    """The default chain (the network, the static refinement ahead; objects, iSAM2 behind):
    the same inputs, so the trajectories agree to the run-to-run noise of Open3D's parallel
    sums (~1e-11 m between two one-thread runs)."""
    (seq, seq_out), (ahead, ahead_out) = (_run(kitti_extract, {}, flag) for flag in (False, True))
    assert seq.error is None and ahead.error is None
    assert np.abs(np.array(seq.odometry) - np.array(ahead.odometry)).max() < 1e-9
    assert all(_ran_ahead(ahead))
    for a, b in zip(seq_out[1:], ahead_out[1:]):
        assert np.mean(a.static_mask == b.static_mask) > 0.9999
        assert set(b.stats["stage_ms"]) >= {"network", "refine", "scan_index", "objects"}


def test_an_error_of_a_stage_run_ahead_stops_the_run_at_its_own_scan(kitti_extract):
    """``gt-seg`` checks for GT labels first; KITTI has none: scan 1 fails in both modes, and
    scan 0 is kept (the background's error is raised when scan 1's turn comes)."""
    for lookahead in (False, True):
        result, _ = _run(kitti_extract, {}, lookahead, frontend="gt-seg")
        assert isinstance(result.error, InputError) and "ground-truth dynamic labels" in str(result.error)
        assert result.indices == [0]


@pytest.mark.usefixtures("one_torch_thread")
def test_the_pair_run_ahead_serves_only_a_pair_with_exactly_its_inputs(kitti_extract):
    """A scan read again is another object: the frontend computes that pair itself, as if
    the background run never happened (its stages' motion models are put back)."""
    from flowslam.config import SsfConfig
    from flowslam.frontends.ssf import SsfFrontend

    ds = open_dataset(kitti_extract)
    scans = [ds[i] for i in range(4)]
    served = SsfFrontend(SsfConfig())
    for k, scan in enumerate(scans):  # as the run loop does
        if k + 1 < len(scans):
            served.upcoming(scans[k + 1])
        out_served = served.process(scan)
    assert "ahead_wait_ms" in out_served.stats

    computed = SsfFrontend(SsfConfig())
    for k, scan in enumerate(scans):
        if k + 1 < len(scans):
            computed.upcoming(ds[k + 1])  # a copy, not the object that comes next
        out_computed = computed.process(scan)
    assert "ahead_wait_ms" not in out_computed.stats
    assert np.abs(out_computed.T_prev_curr - out_served.T_prev_curr).max() < 1e-9
    assert np.mean(out_computed.static_mask == out_served.static_mask) > 0.9999


@pytest.mark.usefixtures("one_torch_thread")
def test_a_recording_frontend_keeps_the_two_threads(kitti_extract):
    """``flowslam demo`` and ``flowslam bench`` record the frontend to replay it into the
    other backend: the recorder hands the read-ahead on, and records the same measurements."""
    from flowslam.replay import RecordingFrontend

    config = PipelineConfig(frontend="ssf", backend="isam2", ssf={"refine": {"enabled": False}})
    recorder = RecordingFrontend(make_frontend("ssf", config))
    result = run_pipeline(open_dataset(kitti_extract), recorder, make_backend("isam2", config), range(4))
    assert result.error is None and all(_ran_ahead(result))
    assert not hasattr(RecordingFrontend(make_frontend("kiss-icp", config)), "upcoming")
    plain, _ = _run(kitti_extract, {"refine": {"enabled": False}}, lookahead=True)
    for k in range(1, 4):
        assert np.array_equal(recorder.records[k].T_prev_curr, plain.odometry[k - 1])


def test_the_scan_index_is_built_once_by_whichever_thread_claims_it_first(kitti_extract):
    """``scan_index`` reads only the two scans: with the lookahead, the background thread
    builds it after the refinement unless the caller's thread, coming to wait, claimed it
    first (``ScanIndexStage.claim``); either way once, and the same index; without a claim
    lock (one thread) the stage always builds it."""
    from flowslam.config import SsfConfig
    from flowslam.frontends.ssf_stages import PairState, ScanIndexStage
    from flowslam.sceneflow.refinement.static import RefinedFlow

    ds = open_dataset(kitti_extract)
    prev, frame = ds[0], ds[1]
    stage = ScanIndexStage(SsfConfig())
    empty = np.zeros((0, 3))

    def state(lock):
        s = PairState(prev, frame, [prev], [np.eye(4)], np.eye(4), scan_index_claim=lock)
        s.refined = RefinedFlow(empty, empty, np.eye(4), True, empty)
        return s

    caller_first = state(threading.Lock())
    assert stage.claim(caller_first) is not None and caller_first.scan_index is not None
    built = caller_first.scan_index
    stage.run(caller_first)  # the background thread comes later: nothing to do
    assert caller_first.scan_index is built

    background_first = state(threading.Lock())
    stage.run(background_first)
    assert background_first.scan_index is not None
    assert stage.claim(background_first) is None  # the caller just waits

    one_thread = state(None)
    assert stage.claim(one_thread) is None and one_thread.scan_index is None
    stage.run(one_thread)
    a, b = one_thread.scan_index, background_first.scan_index
    assert np.array_equal(a.surface.points, b.surface.points)
    assert np.array_equal(a.image.window_min, b.image.window_min)
    assert np.array_equal(a.ground.lowest, b.ground.lowest)


@pytest.mark.usefixtures("one_torch_thread")
@pytest.mark.parametrize("retry", [False, True])
def test_early_network_with_lookahead_equals_its_sequential_run(kitti_extract, retry):
    """``ssf.early_network``: the next pair's network and pose start run ahead while the
    static refinement runs in the caller's thread, on the network poses the one-thread run
    uses (scan k's from its pose start): the same outputs. With ``retry`` the first step's
    global start never confirms it, so the recovery re-runs the stages while the next pair's
    run ahead on the same stage objects: the frontend ends and drops those first."""
    options = {"early_network": True, "objects": {"enabled": False}}
    if retry:
        options["recovery"] = {"confirm_translation_m": 0.0}
    (seq, seq_out), (ahead, ahead_out) = (_run(kitti_extract, options, flag) for flag in (False, True))
    assert seq.error is None and ahead.error is None
    assert np.abs(np.array(seq.odometry) - np.array(ahead.odometry)).max() < 1e-9
    for a, b in zip(seq_out[1:], ahead_out[1:]):
        assert np.array_equal(a.flow, b.flow) and np.array_equal(a.static_mask, b.static_mask)
    assert all(_ran_ahead(ahead)) and not any(_ran_ahead(seq))  # a dropped pair starts again once measured
    outcome = ahead.frontend_stats[1]["recovery"]["outcome"]
    assert outcome in (("kept", "recovered") if retry else ("confirmed",))
    assert "refine" in ahead.frontend_stats[2]["stage_ms"] and "network" in ahead.frontend_stats[2]["stage_ms"]


@pytest.mark.usefixtures("one_torch_thread")
def test_early_network_places_the_network_inputs_with_the_pose_start(kitti_extract):
    """The network of pair (k, k+1) sees scan k placed with the pose start's step, not the
    refined one: the first pair's inputs are the default's (no earlier step), later ones differ,
    and the trajectory still composes the refined steps."""
    (early, early_out), (plain, plain_out) = (
        _run(kitti_extract, {"objects": {"enabled": False}, **extra}, True) for extra in ({"early_network": True}, {}))
    assert np.array_equal(early_out[1].flow, plain_out[1].flow)
    assert not np.array_equal(early_out[3].flow, plain_out[3].flow)
    steps = np.array(early.odometry)
    assert np.abs(steps - np.array(plain.odometry)).max() < 0.05  # refined steps, a few cm apart at most
