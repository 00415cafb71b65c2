"""Training of the scene-flow network (``flowslam train``), on CPU or GPU, one or many processes.

Data: any sequences ``flowslam.datasets.open_dataset`` reads that carry GT flow and
GT poses (the simulator's output, Argoverse-2-format logs with flow labels). Each
sample is built by ``samples.training_sample``: frames compensated with a
*deliberately corrupted* GT prior, targets = residual flow + dynamic labels.

Loss: ``scene_adaptive_loss`` (MambaFlow Eqs. 15-18) or ``deflow_loss`` on the
residual flow of points inside the grid, plus ``bce_weight`` x BCE on the dynamic logit.

Engineering: rich progress bar (rank 0), a checkpoint every epoch
(``checkpoint_last.pt``; ``checkpoint_best.pt`` by validation EPE), ``resume``,
per-epoch validation (EPE3D, AccStrict, AccRelax, Dynamic IoU on the full flow),
bf16 autocast on CUDA, multi-process data parallel through ``torchrun`` (DDP: NCCL
on GPU, gloo on CPU), a wall-clock budget (``max_minutes``), and
``export_weights`` to write a shippable weights file.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from flowslam.config import load_training_config
from flowslam.config.training import PriorNoise, TrainConfig
from flowslam.errors import InputError
from flowslam.sceneflow.network.samples import Sample, training_indices, training_sample

log = logging.getLogger(__name__)




class FlowSamples(torch.utils.data.Dataset):
    """(sequence, newest frame) pairs of one or more sequences, as training samples.

    ``epoch`` and the item index seed the prior corruption and point sampling, so a
    run is reproducible and every epoch sees new corruptions.
    """

    def __init__(self, paths: list[Path], num_frames: int, max_points: int, noise: PriorNoise, seed: int):
        from flowslam.datasets import open_dataset

        self.datasets = [open_dataset(p) for p in paths]
        for path, ds in zip(paths, self.datasets):
            if ds.gt_poses is None:
                raise InputError(path, "has no GT poses; training needs GT poses and GT flow")
        self.items = [(d, k) for d, ds in enumerate(self.datasets) for k in training_indices(ds, num_frames)]
        if not self.items:
            raise InputError(paths[0] if paths else None, f"no complete {num_frames}-frame samples")
        self.num_frames, self.max_points, self.noise, self.seed = num_frames, max_points, noise, seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> Sample:
        d, newest = self.items[i]
        rng = np.random.default_rng([self.seed, self.epoch, i])
        return training_sample(self.datasets[d], newest, self.num_frames, self.noise, rng, self.max_points)


def collate(samples: list[Sample]) -> dict:
    """Batch for ``SceneFlowNet.forward`` plus concatenated targets."""
    return {
        "points": [[torch.from_numpy(p) for p in s.points] for s in samples],
        "residual": torch.from_numpy(np.concatenate([s.residual for s in samples])),
        "dynamic": torch.from_numpy(np.concatenate([s.dynamic for s in samples]).astype(np.float32)),
        "samples": samples,
    }


# -- distributed helpers --------------------------------------------------------------------


def _dist_init() -> tuple[int, int, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    rank = dist.get_rank() if dist.is_initialized() else 0
    if torch.cuda.is_available():
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        return rank, world, torch.device("cuda", local)
    return rank, world, torch.device("cpu")


def _all_mean(value: float, device: torch.device) -> float:
    if not dist.is_initialized():
        return value
    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return float(t.item()) / dist.get_world_size()


# -- loss and metrics -----------------------------------------------------------------------


def compute_loss(out: dict, batch: dict, config: TrainConfig, device: torch.device) -> torch.Tensor:
    from flowslam.sceneflow.network.losses import deflow_loss, dynamic_bce, scene_adaptive_loss

    valid = out["valid"]
    pred = out["flow"][valid].float()
    gt = batch["residual"].to(device)[valid]
    # the flow loss judges the *full* flow error, which equals the residual error
    flow_loss = scene_adaptive_loss(pred, gt) if config.loss == "scene-adaptive" else deflow_loss(pred, gt)
    bce = dynamic_bce(out["dynamic_logit"].float(), batch["dynamic"].to(device), mask=valid)
    return flow_loss + config.bce_weight * bce


@torch.no_grad()
def evaluate_samples(model, samples: list[Sample], device: torch.device) -> dict:
    """Full-flow metrics (EPE3D, AccStrict, AccRelax, Dynamic IoU) over ``samples``."""
    from flowslam.sceneflow.metrics import acc_relax, acc_strict, dynamic_iou, epe3d
    from flowslam.sceneflow.network.model import full_flow

    model.eval()
    preds, gts, dyn_pred, dyn_gt = [], [], [], []
    for s in samples:
        out = model({"points": [[torch.from_numpy(p).to(device) for p in s.points]]})
        preds.append(full_flow(s.source_points, s.points[-2], out["flow"].float().cpu().numpy()))
        gts.append(s.gt_flow)
        dyn_pred.append(out["dynamic_logit"].float().cpu().numpy() > 0)
        dyn_gt.append(s.dynamic)
    pred, gt = np.concatenate(preds), np.concatenate(gts)
    return {
        "epe3d_m": epe3d(pred, gt),
        "acc_strict": acc_strict(pred, gt),
        "acc_relax": acc_relax(pred, gt),
        "dynamic_iou": dynamic_iou(np.concatenate(dyn_pred), np.concatenate(dyn_gt)),
        "samples": len(samples),
    }


# -- the loop -------------------------------------------------------------------------------


def _checkpoint(path: Path, model, optimizer, scheduler, epoch: int, step: int, best: float, config: TrainConfig):
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "model": model.state_dict(),
            "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "epoch": epoch,
            "step": step,
            "best_epe": best,
            "model_config": model.config.model_dump(),
            "train_config": json.loads(config.model_dump_json()),
        },
        tmp,
    )
    os.replace(tmp, path)


def _initial_state(path: Path, model_config: dict) -> dict:
    """State dict of a weights file or a training checkpoint, checked against ``model_config``."""
    payload = torch.load(path, map_location="cpu", weights_only=True)
    state = payload.get("state_dict", payload.get("model"))
    if state is None or payload.get("model_config") != model_config:
        raise InputError(path, "is not a weights file or checkpoint of this model configuration")
    return state


def train(config: TrainConfig, resume: Path | None = None, progress: bool = True) -> dict:
    """Run a training; returns the final validation metrics and paths (rank 0)."""
    from flowslam.sceneflow.network.model import ModelConfig, SceneFlowNet

    rank, world, device = _dist_init()
    torch.manual_seed(config.seed)
    if config.num_threads and device.type == "cpu":
        torch.set_num_threads(config.num_threads)
    train_set = FlowSamples(config.data, config.num_frames, config.max_points, config.prior_noise, config.seed)
    val_set = None
    if config.val:
        val_set = FlowSamples(config.val, config.num_frames, config.max_points, config.prior_noise, config.seed + 1)
        step_ = max(1, len(val_set) // config.val_samples)
        val_samples = [val_set[i] for i in range(0, len(val_set), step_)][: config.val_samples]

    model = SceneFlowNet(
        ModelConfig.preset(config.model_preset, num_frames=config.num_frames, **config.model_overrides)
    ).to(device)
    if config.init_weights is not None:
        model.load_state_dict(_initial_state(config.init_weights, model.config.model_dump()))
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sampler = torch.utils.data.DistributedSampler(train_set, shuffle=True, seed=config.seed) if world > 1 else None
    loader = torch.utils.data.DataLoader(
        train_set, batch_size=config.batch_size, shuffle=sampler is None, sampler=sampler,
        collate_fn=collate, num_workers=config.num_workers, generator=torch.Generator().manual_seed(config.seed),
    )
    total_steps = max(1, config.epochs * len(loader))
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, config.lr, total_steps=total_steps, pct_start=0.1)
    start_epoch, step, best = 0, 0, math.inf
    out_dir = Path(config.out_dir)
    if rank == 0:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "train_config.json").write_text(config.model_dump_json(indent=2))
    if resume is not None:
        ckpt = torch.load(resume, map_location=device, weights_only=True)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        scheduler.load_state_dict(ckpt["scheduler"])
        scheduler.total_steps = total_steps  # resuming with more epochs extends the schedule
        start_epoch, step, best = ckpt["epoch"] + 1, ckpt["step"], ckpt["best_epe"]
        log.info("resumed from %s at epoch %d", resume, start_epoch)

    autocast = (
        torch.autocast("cuda", dtype=torch.bfloat16) if (config.amp and device.type == "cuda") else nullcontext()
    )
    history = []
    t0 = time.monotonic()
    bar = None
    if progress and rank == 0:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                       TextColumn("loss {task.fields[loss]:.4f}"), TimeElapsedColumn())
        bar.start()
    try:
        for epoch in range(start_epoch, config.epochs):
            train_set.epoch = epoch
            if sampler is not None:
                sampler.set_epoch(epoch)
            task = bar.add_task(f"epoch {epoch + 1}/{config.epochs}", total=len(loader), loss=0.0) if bar else None
            net.train()
            losses = []
            for batch in loader:
                with autocast:
                    out = net({"points": [[p.to(device) for p in s] for s in batch["points"]]})
                    loss = compute_loss(out, batch, config, device)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
                optimizer.step()
                scheduler.step()
                step += 1
                losses.append(float(loss.detach()))
                if rank == 0 and bar is None and step % 20 == 0:
                    log.info("epoch %d step %d loss %.4f (%.1f min)", epoch, step, np.mean(losses[-20:]),
                             (time.monotonic() - t0) / 60)
                if bar:
                    bar.update(task, advance=1, loss=float(np.mean(losses[-20:])))
            record = {"epoch": epoch, "step": step, "world_size": world,
                      "train_loss": _all_mean(float(np.mean(losses)), device),
                      "minutes": (time.monotonic() - t0) / 60}
            if val_set is not None and rank == 0:
                record.update({f"val_{k}": v for k, v in evaluate_samples(model, val_samples, device).items()})
            history.append(record)
            if rank == 0:
                log.info("epoch %d: %s", epoch, record)
                metric = record.get("val_epe3d_m", record["train_loss"])
                _checkpoint(out_dir / "checkpoint_last.pt", model, optimizer, scheduler, epoch, step, best, config)
                if metric < best:
                    best = metric
                    _checkpoint(out_dir / "checkpoint_best.pt", model, optimizer, scheduler, epoch, step, best, config)
                (out_dir / "history.json").write_text(json.dumps(history, indent=2))
            if config.max_minutes is not None and (time.monotonic() - t0) / 60 > config.max_minutes:
                log.warning("time budget of %.1f min reached after epoch %d", config.max_minutes, epoch)
                break
    finally:
        if bar:
            bar.stop()
        if dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()
    return {"history": history, "out_dir": str(out_dir), "best": best, "rank": rank, "world": world}


def export_weights(checkpoint: Path, out_path: Path) -> str:
    """Write a shippable weights file (+ .sha256) from a training checkpoint; returns its hash."""
    from flowslam.sceneflow.network.weights import save_weights

    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=True)
    meta = {
        "epoch": ckpt["epoch"],
        "best_val_epe_m": ckpt["best_epe"],
        "train_config": ckpt["train_config"],
    }
    return save_weights(out_path, ckpt["model_config"], ckpt["model"], meta)


def main(argv: list[str] | None = None) -> None:
    """``python -m flowslam.sceneflow.network.train CONFIG [--resume CKPT]`` (for torchrun); CONFIG
    is a run config YAML (its ``training:`` section) or a TrainConfig YAML/JSON."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path, help="run config YAML (training: section) or TrainConfig YAML/JSON")
    parser.add_argument("--resume", type=Path)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    config = load_training_config(args.config)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    train(config, resume=args.resume, progress=not args.no_progress)


if __name__ == "__main__":  # pragma: no cover
    main()
