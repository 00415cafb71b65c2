"""Training side of the scene-flow network: samples, training/resume/export, weights safety,
the ssf frontend on exported weights, and multi-process (DDP, gloo) training."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from flowslam import geometry
from flowslam.datasets import open_dataset
from flowslam.errors import InputError
from flowslam.config import PriorNoise, TrainConfig
from flowslam.sceneflow.network.samples import frames_to_sample, noisy_priors, training_sample
from flowslam.sceneflow.network.train import export_weights, train
from flowslam.sceneflow.network.weights import load_weights

NO_NOISE = PriorNoise(max_translation_m=0, max_yaw_deg=0, max_z_m=0, max_roll_pitch_deg=0, p_no_prior=0)


@pytest.fixture(scope="module")
def sim_seq(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "dt"
    simulate(out, preset="dt", frames=8, seed=11, sensor="vlp32c")
    return out


def test_exact_prior_leaves_static_residual_zero(sim_seq):
    ds = open_dataset(sim_seq)
    s = training_sample(ds, 6, 5, NO_NOISE, np.random.default_rng(0), max_points=4096)
    static = ~s.dynamic
    assert static.sum() > 1000 and s.dynamic.sum() > 10
    np.testing.assert_allclose(s.residual[static], 0, atol=1e-4)  # float32 points
    # dynamic points: the residual is the object's own motion, seen in the newest frame
    assert np.median(np.linalg.norm(s.residual[s.dynamic], axis=1)) > 0.05
    # the compensated source is the source moved by the exact T_{k,k-1}
    T = geometry.relative(ds.gt_poses[6], ds.gt_poses[5])
    np.testing.assert_allclose(s.T_new_src, T, atol=1e-9)


def test_noisy_prior_is_bounded_and_sometimes_absent():
    poses = np.stack([geometry.from_euler("z", 0.01 * k, t=[k, 0.1 * k, 0]) for k in range(5)])
    rng = np.random.default_rng(1)
    noise = PriorNoise()
    errs, identities = [], 0
    for _ in range(300):
        pri = noisy_priors(poses, noise, rng)
        if all(np.allclose(p, np.eye(4)) for p in pri):
            identities += 1
            continue
        E = pri[3] @ geometry.inv(geometry.relative(poses[4], poses[3]))  # the error, in frame k
        errs.append((geometry.translation_norm(E), np.degrees(geometry.rotation_angle(E))))
    errs = np.array(errs)
    assert 10 < identities < 60  # p_no_prior = 0.1
    assert errs[:, 0].max() <= np.hypot(1.5, 0.1) + 1e-9 and errs[:, 0].max() > 1.0
    assert errs[:, 1].max() <= 5.1 and errs[:, 1].max() > 3.0


def test_prior_noise_size_mixture_draws_smaller_errors():
    poses = np.stack([geometry.from_euler("z", 0.01 * k, t=[k, 0.1 * k, 0]) for k in range(5)])

    def newest_step_errors(noise, n=400):
        rng = np.random.default_rng(3)
        out = []
        for _ in range(n):
            pri = noisy_priors(poses, noise, rng)
            E = pri[3] @ geometry.inv(geometry.relative(poses[4], poses[3]))
            out.append(geometry.translation_norm(E))
        return np.array(out)

    full = newest_step_errors(PriorNoise(p_no_prior=0))
    mixed = newest_step_errors(PriorNoise(p_no_prior=0, scale_exponent=2.0))
    # E[u^2] = 1/3: a third of the size on average, the full range still reachable
    assert 0.2 < mixed.mean() / full.mean() < 0.5
    assert mixed.max() > 0.9 and np.mean(mixed < 0.1) > 0.15 > np.mean(full < 0.1)


def test_inference_sample_reads_no_ground_truth(sim_seq):
    ds = open_dataset(sim_seq)
    frames = [ds[i] for i in range(2)]
    for f in frames:
        f.gt_flow = f.gt_pose = f.gt_dynamic = None  # nothing to leak
    s = frames_to_sample(frames, [np.eye(4), np.eye(4)], max_points=1000)
    assert s.residual is None and len(s.points) == 2 and s.points[0].shape == (1000, 3)


def test_loader_workers_build_the_same_batches(sim_seq):
    """``training.num_workers``: samples built in worker processes equal those built in
    the training process (each depends only on seed, epoch and index)."""
    from flowslam.sceneflow.network.train import FlowSamples, collate

    data = FlowSamples([sim_seq], 5, 2048, PriorNoise(), seed=3)
    data.epoch = 1
    batches = {}
    for workers in (0, 2):
        loader = torch.utils.data.DataLoader(data, batch_size=2, shuffle=True, collate_fn=collate,
                                             num_workers=workers, generator=torch.Generator().manual_seed(3))
        batches[workers] = list(loader)
    assert len(batches[0]) == len(batches[2]) == 2  # frames 4..7 of the 8-frame sequence
    for a, b in zip(batches[0], batches[2]):
        np.testing.assert_array_equal(a["residual"].numpy(), b["residual"].numpy())
        np.testing.assert_array_equal(a["dynamic"].numpy(), b["dynamic"].numpy())
        for pa, pb in zip(a["points"], b["points"]):
            for x, y in zip(pa, pb):
                np.testing.assert_array_equal(x.numpy(), y.numpy())


def _config(sim_seq, out_dir, **kw):
    base = dict(data=[str(sim_seq)], val=[str(sim_seq)], out_dir=str(out_dir), epochs=2, batch_size=2,
                max_points=1024, val_samples=2, num_frames=2, model_overrides={"half_extent": 25.6})
    base.update(kw)
    return TrainConfig(**base)


def test_train_resume_export_and_run_ssf(sim_seq, tmp_path):
    cfg = _config(sim_seq, tmp_path / "run", epochs=1)
    first = train(cfg, progress=False)
    assert len(first["history"]) == 1 and (tmp_path / "run" / "checkpoint_last.pt").is_file()
    assert np.isfinite(first["history"][0]["val_epe3d_m"])
    resumed = train(_config(sim_seq, tmp_path / "run", epochs=2), resume=tmp_path / "run" / "checkpoint_last.pt",
                    progress=False)
    assert [h["epoch"] for h in resumed["history"]] == [1]
    digest = export_weights(tmp_path / "run" / "checkpoint_last.pt", tmp_path / "w.pt")
    payload = load_weights(tmp_path / "w.pt")
    assert payload["model_config"]["num_frames"] == 2 and len(digest) == 64

    from flowslam.config import load_config
    from flowslam.registry import make_frontend

    frontend = make_frontend("ssf", load_config(**{"ssf.network.weights": str(tmp_path / "w.pt")}))
    ds = open_dataset(sim_seq)
    assert frontend.process(ds[0]).T_prev_curr is None
    out = frontend.process(ds[1])
    assert out.flow.shape == ds[0].points.shape  # flow for every point of the previous scan
    assert out.static_mask.shape == (len(ds[0].points),) and geometry.is_se3(out.T_prev_curr, 1e-6)


def test_training_starts_from_given_weights(sim_seq, tmp_path):
    from flowslam.sceneflow.network.model import ModelConfig, SceneFlowNet
    from flowslam.sceneflow.network.train import _initial_state
    from flowslam.sceneflow.network.weights import save_weights

    cfg = _config(sim_seq, tmp_path / "run", epochs=1, val=[])
    model = SceneFlowNet(ModelConfig.preset("tiny", num_frames=2, half_extent=25.6))
    torch.nn.init.constant_(model.pillars.linear.weight, 0.125)
    save_weights(tmp_path / "init.pt", model.config.model_dump(), model.state_dict())
    state = _initial_state(tmp_path / "init.pt", model.config.model_dump())
    assert torch.equal(state["pillars.linear.weight"], model.pillars.linear.weight)
    with pytest.raises(InputError, match="not a weights file or checkpoint of this model"):
        _initial_state(tmp_path / "init.pt", {**model.config.model_dump(), "d_state": 4})
    train(cfg.model_copy(update={"init_weights": tmp_path / "init.pt", "lr": 1e-9}), progress=False)
    after = torch.load(tmp_path / "run" / "checkpoint_last.pt", weights_only=True)["model"]
    torch.testing.assert_close(after["pillars.linear.weight"], model.pillars.linear.weight, atol=1e-5, rtol=0)


def test_tampered_or_unhashed_weights_are_refused(sim_seq, tmp_path):
    from flowslam.sceneflow.network.weights import save_weights

    path = tmp_path / "w.pt"
    save_weights(path, {"num_frames": 2}, {"a": torch.zeros(3)})
    assert load_weights(path)["state_dict"]["a"].shape == (3,)
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="differs from the recorded"):
        load_weights(path)
    (tmp_path / "w.pt.sha256").unlink()
    with pytest.raises(InputError, match="no recorded hash"):
        load_weights(path)


def test_ddp_two_gloo_processes(sim_seq, tmp_path):
    cfg = _config(sim_seq, tmp_path / "ddp", epochs=1, val=[])
    (tmp_path / "cfg.json").write_text(cfg.model_dump_json())
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         "-m", "flowslam.sceneflow.network.train", str(tmp_path / "cfg.json"), "--no-progress"],
        capture_output=True, text=True, env=env, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    history = json.loads((tmp_path / "ddp" / "history.json").read_text())
    assert history[0]["world_size"] == 2 and np.isfinite(history[0]["train_loss"])
    # each rank saw half of the samples: 6 samples / (2 ranks x batch 2) -> 2 steps
    assert history[0]["step"] == 2


def test_shipped_weights_load_and_fit_the_budget():
    from flowslam.sceneflow.network.weights import build_model, shipped_weights

    path = shipped_weights()
    assert path.stat().st_size <= 15 * 2**20
    payload = load_weights(path)  # hash-checked, weights_only
    model = build_model(payload)
    assert model.config.num_frames == 5 and model.count_parameters() > 100_000
