"""``flowslam adapt`` end to end on tiny simulated sequences: the split, the held-out tail
never reaching training, resume, the teacher cache, hashed weights that ``run --weights``
loads, and the report (labels of the simulated data are used only there)."""

import json

import numpy as np
import pytest
import torch

from flowslam.config import load_config
from flowslam.datasets import open_dataset
from flowslam.sceneflow.adapt import adapt, split_frames
from flowslam.sceneflow.adapt.loop import near_best
from flowslam.sceneflow.adapt.samples import window
from flowslam.sceneflow.network.weights import load_weights, sha256_of

from cli_helpers import assert_one_line_error, flowslam

TINY = 1e-9  # --max-minutes that stops after the first epoch


@pytest.fixture(scope="module")
def sim_seq(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "dt"
    simulate(out, preset="dt", frames=10, seed=5, sensor="vlp16")
    return out


def _config(out_dir, frames: int, holdout: float, epochs: int = 2, max_minutes=None, cache_dir=None, **more):
    return load_config(**{
        "dataset.max_frames": frames, "adapt.out_dir": str(out_dir), "adapt.holdout_fraction": holdout,
        "adapt.epochs": epochs, "adapt.max_points": 2048, "adapt.max_minutes": max_minutes,
        "adapt.patience": 5, "adapt.device": "cpu", "adapt.cache_dir": cache_dir, **more})


def _model(checkpoint) -> dict:
    return torch.load(checkpoint, weights_only=True)["model"]


def _assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        torch.testing.assert_close(value, b[key], rtol=1e-4, atol=5e-5, msg=key)


def _differ(a: dict, b: dict) -> bool:
    return any(not torch.allclose(v, b[k], rtol=1e-4, atol=5e-5) for k, v in a.items())


def test_split_keeps_a_tail_of_at_least_two_scans():
    assert split_frames(10, 0.2) == 8
    assert split_frames(10, 0.05) == 8  # at least 2 held out
    assert split_frames(8, 0.25) == 6 and split_frames(10, 0.4) == 6
    with pytest.raises(ValueError, match="too few"):
        split_frames(3, 0.2)


@pytest.mark.parametrize("value, best, start, tolerance, written", [
    (0.104, 0.100, 0.120, 0.05, True),   # within 5 % of the best, better than the start
    (0.106, 0.100, 0.120, 0.05, False),  # beyond the tolerance
    (0.1005, 0.100, 0.101, 0.01, True),
    (0.102, 0.100, 0.101, 0.05, False),  # within the tolerance, but worse than the starting weights
])
def test_an_epoch_is_written_when_near_the_best_and_not_worse_than_the_start(value, best, start, tolerance, written):
    assert near_best(value, best, start, tolerance) is written


def test_window_repeats_the_first_scan_like_inference():
    assert window([3, 4, 5, 6], 4, 5) == [3, 3, 3, 3, 4]
    assert window([3, 4, 5, 6], 6, 3) == [4, 5, 6]


@pytest.fixture(scope="module")
def runs(sim_seq, tmp_path_factory, one_torch_thread_module):
    """Four small runs (2 epochs of 5 training pairs each) sharing one teacher cache
    (``adapt.cache_dir``): ``long`` runs the teacher over 10 scans, the others read the
    first 8 of that run (the teacher is causal), so all see exactly the same teacher:

    - ``long``: 10 scans, tail 4, stopped after epoch 1;
    - ``cut``: 8 scans, tail 2: the same 5 training pairs, a shorter, different tail;
      stopped after epoch 1 (max_minutes), then resumed;
    - ``fewer``: 8 scans, tail 3: one training pair fewer (the contrast);
    - ``whole``: 8 scans, both epochs without a stop.
    """
    root = tmp_path_factory.mktemp("adapt")
    out = {"root": root}
    shared = {"cache_dir": str(root / "teacher")}
    out["long"] = adapt([sim_seq], _config(root / "long", 10, 0.4, max_minutes=TINY, **shared), root / "long.pt",
                        progress=False)
    out["long_epoch1"] = _model(root / "long" / "checkpoint_last.pt")
    out["teacher_mtimes"] = {p: p.stat().st_mtime_ns for p in (root / "teacher").rglob("*")}
    cfg = _config(root / "cut", 8, 0.25, max_minutes=TINY, **shared)
    out["cut_first"] = adapt([sim_seq], cfg, root / "cut.pt", progress=False)
    out["cut_epoch1"] = _model(root / "cut" / "checkpoint_last.pt")
    out["cut"] = adapt([sim_seq], _config(root / "cut", 8, 0.25, **shared), root / "cut.pt", resume=True,
                       progress=False)
    out["fewer"] = adapt([sim_seq], _config(root / "fewer", 8, 0.375, max_minutes=TINY, **shared), root / "fewer.pt",
                         progress=False)
    out["fewer_epoch1"] = _model(root / "fewer" / "checkpoint_last.pt")
    out["whole"] = adapt([sim_seq], _config(root / "whole", 8, 0.25, **shared), root / "whole.pt", progress=False)
    return out


@pytest.fixture(scope="module")
def one_torch_thread_module():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_the_held_out_tail_never_reaches_training(runs):
    cut, long = runs["cut_first"], runs["long"]
    assert cut["split"][next(iter(cut["split"]))] == {"train_frames": [0, 5], "holdout_frames": [6, 7]}
    assert long["split"][next(iter(long["split"]))] == {"train_frames": [0, 5], "holdout_frames": [6, 9]}
    meta = load_weights(runs["root"] / "long.pt")["meta"]
    train_pairs = next(iter(meta["train_pairs"].values()))
    held = set(next(iter(meta["holdout_frames"].values())))
    assert train_pairs == [1, 2, 3, 4, 5]
    assert not any(set(window(list(range(10)), k, 5)) & held for k in train_pairs)
    # The strong form: a different, longer tail changes nothing the training saw, so the
    # weights after the first epoch are the same (one teacher run serves both: two runs
    # of the same scans differ, Open3D's sums are not bit-reproducible).
    _assert_same_weights(runs["cut_epoch1"], runs["long_epoch1"])
    assert _differ(runs["cut_epoch1"], runs["fewer_epoch1"])  # one pair more or less shows


def test_resume_continues_where_the_run_stopped(runs):
    first, resumed, whole = runs["cut_first"], runs["cut"], runs["whole"]
    assert [h["epoch"] for h in first["history"]] == [0, 1]
    assert [h["epoch"] for h in resumed["history"]] == [0, 1, 2]
    assert resumed["history"][:2] == first["history"][:2]
    stopped_then_resumed = _model(runs["root"] / "cut" / "checkpoint_last.pt")
    uninterrupted = _model(runs["root"] / "whole" / "checkpoint_last.pt")
    _assert_same_weights(stopped_then_resumed, uninterrupted)
    # The teacher ran once, for the 10-scan run: every later run read its cache.
    assert {p: p.stat().st_mtime_ns for p in (runs["root"] / "teacher").rglob("*")} == runs["teacher_mtimes"]
    assert not (runs["root"] / "cut" / "cache").exists()


def test_a_cached_teacher_serves_the_prefix_of_its_run(runs):
    from flowslam.sceneflow.adapt.teacher import load_teacher

    (folder,) = list((runs["root"] / "teacher").glob("teacher-*"))
    full = load_teacher(folder)
    assert full.frames == list(range(10)) and sorted(full.pairs) == list(range(1, 10))
    part = load_teacher(folder, list(range(8)))
    assert part.frames == list(range(8)) and sorted(part.pairs) == list(range(1, 8))
    assert np.array_equal(part.pairs[7].flow, full.pairs[7].flow) and np.array_equal(part.poses[7], full.poses[7])
    assert load_teacher(folder, list(range(11))) is None  # longer than the cached run: recomputed
    assert load_teacher(folder, list(range(1, 8))) is None  # another start


def test_resume_refuses_other_sequences(runs, sim_seq, tmp_path):
    from flowslam.errors import InputError
    from flowslam.simulation import simulate

    other = tmp_path / "other"
    simulate(other, preset="static", frames=8, seed=1, sensor="vlp16")
    with pytest.raises(InputError, match="other starting weights or sequences"):
        adapt([other], _config(runs["root"] / "cut", 8, 0.25), tmp_path / "x.pt", resume=True, progress=False)


def test_weights_are_hashed_and_record_their_origin(runs):
    path = runs["root"] / "cut.pt"
    assert (runs["root"] / "cut.pt.sha256").read_text().split()[0] == sha256_of(path) == runs["cut"]["sha256"]
    meta = load_weights(path)["meta"]
    assert meta["adapted_from_sha256"] == sha256_of(meta["adapted_from"])
    assert meta["best_epoch"] == runs["cut"]["best_epoch"] and meta["written_epoch"] == runs["cut"]["written_epoch"]
    report = json.loads((runs["root"] / "cut" / "report.json").read_text())
    assert report["sha256"] == runs["cut"]["sha256"]


def test_report_compares_both_weights_on_the_tail(runs):
    (scores,) = runs["cut"]["report"].values()
    for which in ("start", "adapted"):
        s = scores[which]
        assert 0 <= s["data_term_m"] <= 2.0 and np.isfinite(s["teacher_epe_m"])
        assert 0 <= s["rpe1_trans_m"] < 0.5  # simulated data has GT poses: the report uses them
        assert np.isfinite(s["gt_flow"]["EPE3D"])
        assert "objects_ms_median" not in s  # the costs are the refined runs'
        refined = scores[f"{which}_refined"]
        assert 0 < refined["objects_ms_median"] < refined["frame_ms_median"]
        assert refined["object_candidates_mean"] >= 0 and refined["objects_mean"] >= 0
        assert 0 <= refined["rpe1_trans_m"] < 0.5 and np.isfinite(refined["gt_flow"]["EPE3D"])
    # The refined frontend with the teacher's own weights is the teacher (up to the run's
    # later start): far closer to it than the network alone.
    assert scores["start_refined"]["teacher_epe_m"] < 0.5 * scores["start"]["teacher_epe_m"]
    # The best epoch has the lowest held-out EPE against the teacher on the fixed held-out
    # samples (epoch 0: the start); the written one is the latest within 1 % of it.
    history = runs["cut"]["history"]
    score = {h["epoch"]: h["holdout_samples_teacher_epe_m"] for h in history}
    best = min(score, key=lambda e: (score[e], e))
    assert runs["cut"]["best_epoch"] == best
    assert runs["cut"]["written_epoch"] == max(e for e in score if score[e] <= score[best] * 1.01)


def test_run_uses_the_adapted_weights(runs, sim_seq, tmp_path):
    proc = flowslam("run", "-f", "ssf", "-b", "odometry", "--weights", runs["root"] / "cut.pt", "--max-frames", 3,
                    "--no-progress", "--output-dir", tmp_path, sim_seq)
    assert proc.returncode == 0, proc.stderr
    run_json = json.loads((tmp_path / "latest" / "run.json").read_text())
    assert runs["cut"]["sha256"] in json.dumps(run_json)
    tampered = tmp_path / "tampered.pt"
    tampered.write_bytes((runs["root"] / "cut.pt").read_bytes() + b"x")
    (tmp_path / "tampered.pt.sha256").write_text((runs["root"] / "cut.pt.sha256").read_text())
    proc = flowslam("run", "-f", "ssf", "--weights", tampered, "--max-frames", 3, "--no-progress",
                    "--output-dir", tmp_path, sim_seq)
    assert_one_line_error(proc, "tampered.pt", "SHA-256")


def test_adapt_cli_bad_input_is_one_line(tmp_path, sim_seq):
    proc = flowslam("adapt", tmp_path / "missing", "--weights-out", tmp_path / "w.pt", "--no-progress")
    assert_one_line_error(proc, "missing")
    proc = flowslam("adapt", sim_seq, "--weights-out", tmp_path / "w.pt", "--max-frames", 3, "--no-progress",
                    "--out-dir", tmp_path / "o")
    assert_one_line_error(proc, str(sim_seq), "too few")
