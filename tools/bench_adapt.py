"""Measurements of ``flowslam adapt`` for the README and the issue's targets (not a test).

Three experiments, each comparing the shipped weights with adapted ones in the same
process:

- ``kitti``: adapt on the real KITTI 00 extract in ``../shared/data`` with the last half
  held out (frames 0-7 train, 8-15 never trained on); network-only ``ssf`` over frames
  0-15, RPE(1) translation RMSE of the held-out pairs 8-15 against
  ``reference_icp_lidar.txt`` (and the KITTI GT); refined ``ssf`` over 0-15 against the
  reference (the "not worse" check).
- ``sim``: simulate ``--train-seeds`` unlabelled ``dt`` sequences and a fresh held-out
  seed; adapt on the former (their labels unused); network-only and refined ``flow-eval``
  metrics (EPE3D, Dynamic IoU) on the held-out seed.
- ``speed``: wall time of ``adapt`` on a 100-frame 64-beam simulated sequence.
- ``gain``: what limits the network alone: on the held-out ``sim`` seed, the network is
  fed GT-compensated scans whose newest prior is off by a known translation (0-40 cm,
  random direction); the mean static-point flow error left shows how much of a prior
  error the network corrects (shipped weights, ``--weights`` and each ``--also``; a
  diagnostic that reads GT, never part of the system; ``--sequence``, ``--device`` and
  ``--points`` run it on any simulated sequence, e.g. on a GPU machine).

    python tools/bench_adapt.py kitti|sim|speed|gain [--out runs/bench_adapt] [--weights W] [--set KEY=VALUE]

``--set adapt.lr=2e-4`` (repeatable) overrides the run config. Writes
``OUT/<experiment>.json``. The machine's load average is printed: timings are upper
bounds on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import yaml

DATA = Path(os.environ.get("FLOWSLAM_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
KITTI = DATA / "kitti-odometry-00-first16"


def _config(overrides: dict, **more):
    from flowslam.config import load_config

    return load_config(**{"frontend": "ssf", **overrides, **more})


def _run(path: Path, config, frames=None):
    """Odometry ``ssf`` run of ``config`` over ``frames`` (default all): the ``RunResult``."""
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend

    dataset = open_dataset(path, config.dataset)
    result = run_pipeline(dataset, make_frontend("ssf", config), make_backend("odometry", config),
                          frames or range(len(dataset)))
    if result.error is not None:
        raise result.error
    return result


def _rpe1(poses: np.ndarray, reference: np.ndarray) -> float:
    from flowslam.evaluation.rpe import rpe

    return rpe(poses, reference, delta=1)["rmse"]


def _adapt(paths: list[Path], config, weights_out: Path) -> dict:
    from flowslam.sceneflow.adapt import adapt

    t0 = time.perf_counter()
    result = adapt(paths, config, weights_out, progress=False)
    result["wall_s"] = time.perf_counter() - t0
    return result


def kitti(out: Path, overrides: dict, weights: Path | None) -> dict:
    from flowslam.datasets import open_dataset
    from flowslam.sceneflow.adapt.report import network_only
    from flowslam.sceneflow.network.weights import shipped_weights
    from flowslam.trajectory import read_trajectory

    reference = read_trajectory(KITTI / "reference_icp_lidar.txt").poses
    gt = np.asarray(open_dataset(KITTI).gt_poses)
    adapted = weights
    record: dict = {}
    if adapted is None:
        adapted = out / "kitti.pt"
        cfg = _config(overrides, **{"adapt.holdout_fraction": 0.5, "adapt.out_dir": str(out / "kitti")})
        result = _adapt([KITTI], cfg, adapted)
        record["adapt"] = {k: result[k] for k in ("best_epoch", "written_epoch", "minutes", "wall_s", "history", "split")}
    tail = list(range(8, 16))
    for name, w in (("shipped", shipped_weights()), ("adapted", adapted)):
        net = _run(KITTI, network_only(_config(overrides), w))
        refined = _run(KITTI, _config(overrides, **{"ssf.network.weights": str(w)}))
        record[name] = {
            "network_only_rpe1_tail_vs_reference_m": _rpe1(net.poses[tail], reference[tail]),
            "network_only_rpe1_tail_vs_gt_m": _rpe1(net.poses[tail], gt[tail]),
            "network_only_rpe1_all_vs_reference_m": _rpe1(net.poses, reference),
            "refined_rpe1_all_vs_reference_m": _rpe1(refined.poses, reference),
            "refined_rpe1_tail_vs_reference_m": _rpe1(refined.poses[tail], reference[tail]),
            "refine_accepted": int(sum(bool(s.get("refine_accepted")) for s in refined.frontend_stats)),
        }
    return record


def sim(out: Path, overrides: dict, weights: Path | None, train_seeds: list[int], test_seed: int,
        frames: int, sensor: str) -> dict:
    from flowslam.flow_eval import evaluate_flow
    from flowslam.sceneflow.adapt.report import network_only
    from flowslam.sceneflow.network.weights import shipped_weights
    from flowslam.simulation import simulate

    paths = []
    for seed in [*train_seeds, test_seed]:
        path = out / "sim" / f"dt-{sensor}-{frames}-{seed}"
        if not (path / "manifest.json").is_file():
            simulate(path, preset="dt", frames=frames, seed=seed, sensor=sensor)
        paths.append(path)
    *train, test = paths
    adapted = weights
    record: dict = {"train": [str(p) for p in train], "test": str(test)}
    if adapted is None:
        adapted = out / "sim.pt"
        result = _adapt(train, _config(overrides, **{"adapt.out_dir": str(out / "sim-adapt")}), adapted)
        record["adapt"] = {k: result[k] for k in ("best_epoch", "written_epoch", "minutes", "wall_s", "history", "report")}
    for name, w in (("shipped", shipped_weights()), ("adapted", adapted)):
        metrics = {}
        for mode, cfg in (("network_only", network_only(_config(overrides), w)),
                          ("refined", _config(overrides, **{"ssf.network.weights": str(w)}))):
            result = evaluate_flow(test, cfg)
            flow = result["flow"]
            metrics[mode] = {k: flow.get(k) for k in ("EPE3D", "AccStrict", "EPE_3way", "EPE_FD", "DynamicIoU")}
            metrics[mode]["ego_trans_m_mean"] = result["ego_motion_error"]["trans_m_mean"]
        record[name] = metrics
    return record


def speed(out: Path, overrides: dict, frames: int, sensor: str) -> dict:
    from flowslam.simulation import simulate

    path = out / "speed" / f"dt-{sensor}-{frames}"
    if not (path / "manifest.json").is_file():
        simulate(path, preset="dt", frames=frames, seed=101, sensor=sensor)
    cfg = _config(overrides, **{"adapt.out_dir": str(out / "speed-adapt")})
    for stale in (out / "speed-adapt").glob("checkpoint_last.pt"):
        stale.unlink()
    result = _adapt([path], cfg, out / "speed.pt")
    return {k: result[k] for k in ("best_epoch", "written_epoch", "minutes", "wall_s", "history")}


def gain(out: Path, weights: list[Path], test_seed: int, frames: int, sensor: str, sequence: Path | None = None,
         device: str = "cpu", points: int = 16384) -> dict:
    import torch

    from flowslam import geometry
    from flowslam.datasets import open_dataset
    from flowslam.sceneflow.network.samples import frames_to_sample
    from flowslam.sceneflow.network.weights import build_model, load_weights, shipped_weights

    dataset = open_dataset(sequence or out / "sim" / f"dt-{sensor}-{frames}-{test_seed}")
    gt = np.asarray(dataset.gt_poses)
    record = {}
    for name, w in [("shipped", shipped_weights())] + [(str(w), w) for w in weights]:
        model = build_model(load_weights(w, require_hash=False)).to(device)
        model.fold_batchnorm()
        rng = np.random.default_rng(0)
        rows = {}
        for err in (0.0, 0.05, 0.1, 0.2, 0.4):
            left, mean_left = [], []
            for k in range(5, len(dataset), 4):
                indices = list(range(k - 4, k + 1))
                phi = rng.uniform(0, 2 * np.pi)
                E = geometry.from_euler("xyz", [0, 0, 0], t=[err * np.cos(phi), err * np.sin(phi), 0])
                T_new_world = geometry.inv(gt[k])
                priors = [E @ T_new_world @ gt[i] for i in indices[:-1]] + [np.eye(4)]
                scans = [dataset[i] for i in indices]
                sample = frames_to_sample(scans, priors, points)
                with torch.inference_mode():
                    res = model({"points": [[torch.from_numpy(p).to(device) for p in sample.points]]})["flow"]
                res = res.float().cpu().numpy()
                flow = sample.points[-2] - sample.source_points + res
                static = ~scans[-2].gt_dynamic[sample.source_index]
                d = (flow - scans[-2].gt_flow[sample.source_index])[static]
                left.append(np.linalg.norm(d, axis=1).mean())
                mean_left.append(np.linalg.norm(d.mean(axis=0)))
            rows[f"{err:.2f}"] = {"static_epe_m": float(np.mean(left)), "mean_static_error_m": float(np.mean(mean_left))}
        record[name] = rows
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", choices=["kitti", "sim", "speed", "gain"])
    ap.add_argument("--out", type=Path, default=Path("runs/bench_adapt"))
    ap.add_argument("--weights", type=Path, help="Evaluate these adapted weights instead of adapting.")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE run-config override (YAML value).")
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[201, 202, 203])
    ap.add_argument("--test-seed", type=int, default=299)
    ap.add_argument("--frames", type=int, default=30, help="sim: frames per sequence; speed: 100.")
    ap.add_argument("--sensor", default="hdl64")
    ap.add_argument("--also", type=Path, action="append", default=[], help="gain: more weights to compare.")
    ap.add_argument("--sequence", type=Path, help="gain: this simulated sequence instead of the held-out seed's.")
    ap.add_argument("--device", default="cpu", help="gain: torch device of the network.")
    ap.add_argument("--points", type=int, default=16384, help="gain: points sampled per scan.")
    args = ap.parse_args()
    overrides = {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in args.set)}
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    if args.experiment == "kitti":
        record = kitti(args.out, overrides, args.weights)
    elif args.experiment == "sim":
        record = sim(args.out, overrides, args.weights, args.train_seeds, args.test_seed, args.frames, args.sensor)
    elif args.experiment == "gain":
        weights = [w for w in (args.weights, *args.also) if w is not None]
        record = gain(args.out, weights, args.test_seed, args.frames, args.sensor, args.sequence, args.device,
                      args.points)
    else:
        record = speed(args.out, overrides, 100 if args.frames == 30 else args.frames, args.sensor)
    record["overrides"] = overrides
    (args.out / f"{args.experiment}.json").write_text(json.dumps(record, indent=2, default=str))
    summary = {k: v for k, v in record.items() if k not in ("adapt",)}
    if "adapt" in record:
        summary["adapt"] = {k: v for k, v in record["adapt"].items() if k in ("best_epoch", "written_epoch", "minutes", "wall_s")}
        summary["history"] = [{k: round(v, 4) if isinstance(v, float) else v for k, v in h.items()
                               if k.startswith("holdout") or k == "epoch"} for h in record["adapt"]["history"]]
    print(json.dumps(summary, indent=1, default=str))


if __name__ == "__main__":
    main()
