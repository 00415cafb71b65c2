"""``flowslam adapt``: fine-tune the scene-flow network on unlabelled sequences.

1. Split: the last ``adapt.holdout_fraction`` of each sequence's frames (at least 2) is
   the held-out tail; training pairs use only scans before it.
2. Teacher: the full ``ssf`` pipeline runs once over each sequence with the starting
   weights (``teacher.py``, cached).
3. Training: each step feeds a pair built as at inference (``samples.py``: the
   system's own poses, plus augmentation) and minimises
   ``distill + data + L_mot + L_SC + L_CD`` (weights ``adapt.loss``; terms in
   ``flowslam.sceneflow.network.self_supervised``).
4. After every epoch the held-out tail's pairs are scored without labels: the
   network's EPE against the teacher on fixed held-out samples (teacher poses with a
   seeded draw of the training prior errors; ``sample_scores``). The latest epoch within
   ``select_tolerance`` of the best score and no worse than the starting weights' score
   is written (``near_best``), and the run stops after
   ``patience`` epochs without a new best. Epoch "0" is the starting weights: if no
   epoch comes near them, the written weights are the starting ones.
   (A network-only run over the tail was tried as the per-epoch score: it jumps from
   epoch to epoch with the run's compounding pose errors and picked epochs that were
   worse on a held-out seed; it is the final report's measure instead.)
5. The chosen epoch's weights are written with their SHA-256 sidecar; ``report.py``
   compares them with the starting weights on the tails in pipeline conditions.

Checkpoints (``checkpoint_last.pt``, every epoch) make a run resumable; CUDA is used
when present (``adapt.device``).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from flowslam.config import PipelineConfig
from flowslam.errors import InputError
from flowslam.sceneflow.adapt.samples import AdaptSample, adapt_sample
from flowslam.sceneflow.adapt.teacher import Teacher, cache_key, load_teacher, run_teacher


SELECT_BY = "samples_teacher_epe_m"
"""The held-out score that picks the best epoch (``sample_scores``)."""


@dataclass
class Sequence:
    """One input sequence: its reader, the frames of the run and the split."""

    path: Path
    dataset: object
    frames: list[int]
    tail_start: int
    """Position in ``frames`` of the first held-out scan."""
    teacher: Teacher | None = None

    @property
    def train_pairs(self) -> list[int]:
        """Newest-scan indices of the training pairs (every input scan before the tail)."""
        return self.frames[1:self.tail_start]

    @property
    def holdout_pairs(self) -> list[int]:
        """Newest-scan indices of the held-out pairs (source and target in the tail)."""
        return self.frames[self.tail_start + 1:]

    @property
    def holdout_frames(self) -> list[int]:
        return self.frames[self.tail_start:]

    def scoring_frames(self, num_frames: int) -> list[int]:
        """The frames a held-out score runs over: the tail and the ``num_frames`` scans
        before it (they give the network its history and the run its velocity; their
        pairs are not scored)."""
        return self.frames[max(0, self.tail_start - num_frames):]


def split_frames(n: int, holdout_fraction: float) -> int:
    """Position of the first held-out scan among ``n`` scans: the tail holds
    ``ceil(fraction * n)`` scans, at least 2; at least 2 scans stay for training."""
    tail = max(2, math.ceil(holdout_fraction * n))
    if n - tail < 2:
        raise ValueError(f"{n} scans are too few: adaptation needs 2 to train on and {tail} held out")
    return n - tail


def open_sequences(paths: list[Path], config: PipelineConfig) -> list[Sequence]:
    from flowslam.datasets import frame_range, open_dataset

    out = []
    for path in paths:
        dataset = open_dataset(path, config.dataset)
        frames = list(frame_range(len(dataset), config.dataset))
        try:
            start = split_frames(len(frames), config.adapt.holdout_fraction)
        except ValueError as e:
            raise InputError(path, str(e)) from None
        out.append(Sequence(Path(path), dataset, frames, start))
    return out


def _device(choice: str) -> torch.device:
    from flowslam.sceneflow.network.device import inference_device

    if choice == "cuda" and not torch.cuda.is_available():
        raise InputError(None, "adapt.device is 'cuda' but torch sees no CUDA device")
    return inference_device(choice)


# -- the loss ---------------------------------------------------------------------------------


def pair_loss(out: dict, s: AdaptSample, config: PipelineConfig, rows: slice) -> tuple[torch.Tensor, dict]:
    """The adaptation loss of one pair (``rows`` of the batched network output) and its parts."""
    from flowslam.sceneflow.network import self_supervised as ss

    a, w = config.adapt, config.adapt.loss
    dev = out["flow"].device
    residual, logit, valid = out["flow"][rows].float(), out["dynamic_logit"][rows].float(), out["valid"][rows]
    src = torch.from_numpy(s.sample.source_points).to(dev)
    compensated = torch.from_numpy(s.sample.points[-2]).to(dev)
    flow = compensated - src + residual  # AV2 convention, sensor frame k
    target = s.target
    parts = {}
    if w.distill:
        parts["distill"] = w.distill * ss.distillation_loss(
            residual, logit, torch.from_numpy(s.sample.residual).to(dev),
            torch.from_numpy(s.sample.dynamic.astype(np.float32)).to(dev), mask=valid, bce_weight=w.distill_bce,
            max_pos_weight=w.max_pos_weight, calibrated=w.calibrated_bce)
    need_tree = w.data or w.rigid_chamfer
    tree = None
    if need_tree:
        from scipy.spatial import cKDTree

        tree = cKDTree(target)
    if w.data:
        parts["data"] = w.data * ss.chamfer_to_scan((src + flow)[valid], target, a.truncate_m, tree)
    segments = torch.from_numpy(s.segments).to(dev)
    segments = torch.where(valid, segments, torch.full_like(segments, -1))
    if w.motion:
        parts["motion"] = w.motion * ss.rigid_motion_loss(src, flow, segments, a.min_segment_points)
    if w.consistency:
        parts["consistency"] = w.consistency * ss.semantic_consistency_loss(
            flow[valid], logit[valid], torch.from_numpy(s.ego_flow).to(dev)[valid], a.consistency_threshold_m)
    if w.rigid_chamfer:
        parts["rigid_chamfer"] = w.rigid_chamfer * ss.rigid_chamfer_loss(
            src, flow, segments, target, a.truncate_m, a.min_segment_points, tree)
    total = sum(parts.values()) if parts else flow.sum() * 0.0
    return total, {k: float(v.detach()) for k, v in parts.items()}


def _forward(model, samples: list[AdaptSample], device: torch.device) -> tuple[dict, list[slice]]:
    out = model({"points": [[torch.from_numpy(p).to(device) for p in s.sample.points] for s in samples]})
    counts = [len(s.sample.source_points) for s in samples]
    ends = np.cumsum(counts)
    return out, [slice(int(e - c), int(e)) for e, c in zip(ends, counts)]


# -- held-out scores --------------------------------------------------------------------------


def holdout_samples(sequences: list[Sequence], config: PipelineConfig, num_frames: int,
                    max_points: int) -> list[AdaptSample]:
    """The held-out pairs as fixed samples: the teacher's poses with prior errors drawn
    once from ``adapt.prior_noise`` (a seeded draw per pair, the same every epoch), the
    errors a network-only run's own poses have."""
    a = config.adapt
    return [adapt_sample(seq.dataset, seq.teacher, k, num_frames, max_points, a.prior_noise,
                         np.random.default_rng([a.seed, 7919, k]))
            for seq in sequences for k in seq.holdout_pairs]


@torch.no_grad()
def sample_scores(model, samples: list[AdaptSample], device: torch.device) -> dict:
    """``teacher_epe_m``: the mean EPE of ``model``'s flow against the teacher's over the
    held-out samples (m); ``static_teacher_epe_m``: the same over the teacher's static
    points. No labels. It selects the best epoch: smooth from epoch to epoch, where a
    network-only run's compounding pose errors make its score jump."""
    model.eval()
    epe, static = [], []
    for s in samples:
        out, _ = _forward(model, [s], device)
        flow = s.sample.points[-2] - s.sample.source_points + out["flow"].float().cpu().numpy()
        error = np.linalg.norm(flow - s.teacher_flow, axis=1)
        epe.append(error.mean())
        static.append(error[s.segments == 0].mean() if (s.segments == 0).any() else np.nan)
    return {"teacher_epe_m": float(np.mean(epe)), "static_teacher_epe_m": float(np.nanmean(static))} if samples else {}


# -- the run ----------------------------------------------------------------------------------


def _teachers(sequences: list[Sequence], config: PipelineConfig, weights_hash: str, cache: Path,
              on_frame: Callable[[], None] | None) -> None:
    for seq in sequences:
        folder = cache / f"teacher-{cache_key(seq.path, seq.frames, config, weights_hash)}"
        seq.teacher = load_teacher(folder, seq.frames)
        if seq.teacher is None:
            seq.teacher = run_teacher(seq.dataset, seq.frames, config, folder,
                                      (lambda _i: on_frame()) if on_frame else None)
        elif on_frame is not None:
            for _ in seq.frames:
                on_frame()


def _save(path: Path, payload: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def adapt(paths: list[Path], config: PipelineConfig, weights_out: Path, resume: bool = False,
          progress: bool = True) -> dict:
    """Adapt ``config.ssf.network.weights`` (None: the shipped weights) to ``paths``; write
    the chosen epoch's weights (``adapt.select_tolerance``) to ``weights_out`` (+
    ``.sha256``). Returns the history, the best and the written epoch, the split, the
    hash and the held-out report (``report.compare_on_holdout``)."""
    from flowslam.sceneflow.adapt.report import compare_on_holdout
    from flowslam.sceneflow.network.weights import build_model, load_weights, save_weights, shipped_weights

    a = config.adapt
    init_path = Path(config.ssf.network.weights or shipped_weights())
    payload = load_weights(init_path, require_hash=config.ssf.network.weights is None)
    init_hash = payload["sha256"]
    config = config.model_copy(deep=True)
    config.ssf.network.weights = init_path
    out_dir = Path(a.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = _device(a.device)
    if a.num_threads and device.type == "cpu":
        torch.set_num_threads(a.num_threads)
    t0 = time.monotonic()
    sequences = open_sequences(paths, config)
    bar = _Bar(progress)
    try:
        bar.stage("teacher (refined ssf)", sum(len(s.frames) for s in sequences))
        _teachers(sequences, config, init_hash, a.cache_dir or out_dir / "cache", bar.advance)
        model = build_model(payload).to(device)
        num_frames = model.config.num_frames
        max_points = a.max_points or config.ssf.network.max_points
        items = [(d, k) for d, seq in enumerate(sequences) for k in seq.train_pairs]
        held = holdout_samples(sequences, config, num_frames, max_points)

        def score() -> dict:
            return {f"samples_{k}": v for k, v in sample_scores(model, held, device).items()}

        torch.manual_seed(a.seed)
        optimizer = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=a.weight_decay)
        steps_per_epoch = math.ceil(len(items) / a.batch_size)
        scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, a.lr, total_steps=a.epochs * steps_per_epoch,
                                                        pct_start=0.15)
        last = out_dir / "checkpoint_last.pt"
        if resume and last.is_file():
            ckpt = torch.load(last, map_location=device, weights_only=True)
            if ckpt["weights_hash"] != init_hash or ckpt["sequences"] != [str(s.path) for s in sequences]:
                raise InputError(last, "was written for other starting weights or sequences; drop --resume")
            model.load_state_dict(ckpt["model"])
            optimizer.load_state_dict(ckpt["optimizer"])
            scheduler.load_state_dict(ckpt["scheduler"])
            history, best, best_epoch = ckpt["history"], ckpt["best"], ckpt["best_epoch"]
            chosen_state, chosen_epoch, start = ckpt["chosen_state"], ckpt["chosen_epoch"], ckpt["epoch"] + 1
        else:
            start_scores = score()
            history = [{"epoch": 0, "minutes": (time.monotonic() - t0) / 60, **_prefixed(start_scores)}]
            best = start_scores.get(SELECT_BY, math.inf)
            chosen_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            best_epoch = chosen_epoch = 0
            start = 1
        for epoch in range(start, a.epochs + 1):
            rng = np.random.default_rng([a.seed, epoch])
            order = rng.permutation(len(items))
            _train_mode(model, a.freeze_norm)
            bar.stage(f"epoch {epoch}/{a.epochs}", steps_per_epoch)
            sums: dict[str, float] = {}
            for b in range(steps_per_epoch):
                batch = [items[i] for i in order[b * a.batch_size:(b + 1) * a.batch_size]]
                samples = [adapt_sample(sequences[d].dataset, sequences[d].teacher, k, num_frames, max_points,
                                        a.prior_noise, rng) for d, k in batch]
                out, rows = _forward(model, samples, device)
                losses = [pair_loss(out, s, config, r) for s, r in zip(samples, rows)]
                loss = sum(x for x, _ in losses) / len(losses)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
                optimizer.step()
                scheduler.step()
                for _, parts in losses:
                    for key, v in parts.items():
                        sums[key] = sums.get(key, 0.0) + v / len(items)
                bar.advance(loss=float(loss.detach()))
            scores = score()
            record = {"epoch": epoch, "minutes": (time.monotonic() - t0) / 60,
                      **{f"train_{k}": v for k, v in sums.items()}, **_prefixed(scores)}
            history.append(record)
            value = scores.get(SELECT_BY, math.inf)
            if value < best:
                best, best_epoch = value, epoch
            if near_best(value, best, history[0].get(f"holdout_{SELECT_BY}", math.inf), a.select_tolerance):
                chosen_epoch = epoch
                chosen_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            _save(last, {"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                         "scheduler": scheduler.state_dict(), "epoch": epoch, "history": history, "best": best,
                         "best_epoch": best_epoch, "chosen_state": chosen_state, "chosen_epoch": chosen_epoch,
                         "weights_hash": init_hash,
                         "sequences": [str(s.path) for s in sequences]})
            (out_dir / "history.json").write_text(json.dumps(history, indent=2))
            if epoch - best_epoch >= a.patience:
                break
            if a.max_minutes is not None and (time.monotonic() - t0) / 60 > a.max_minutes:
                break
    finally:
        bar.stop()
    meta = {"adapted_from": str(init_path), "adapted_from_sha256": init_hash, "best_epoch": best_epoch,
            "written_epoch": chosen_epoch,
            f"holdout_{SELECT_BY}": best, "sequences": [str(s.path) for s in sequences],
            "train_pairs": {str(s.path): s.train_pairs for s in sequences},
            "holdout_frames": {str(s.path): s.holdout_frames for s in sequences},
            "adapt_config": json.loads(a.model_dump_json())}
    digest = save_weights(weights_out, payload["model_config"], chosen_state, meta)
    minutes = (time.monotonic() - t0) / 60
    report = compare_on_holdout(sequences, config, init_path, Path(weights_out), num_frames)
    result = {"weights": str(weights_out), "sha256": digest, "best_epoch": best_epoch,
              "written_epoch": chosen_epoch, "minutes": minutes,
              "history": history, "report": report,
              "split": {str(s.path): {"train_frames": [s.frames[0], s.frames[s.tail_start - 1]],
                                      "holdout_frames": [s.frames[s.tail_start], s.frames[-1]]} for s in sequences}}
    (out_dir / "report.json").write_text(json.dumps(result, indent=2, default=str))
    return result


def near_best(value: float, best: float, start: float, tolerance: float) -> bool:
    """Whether an epoch whose held-out score is ``value`` is written (the latest such epoch
    is): within ``tolerance`` (a fraction) of the ``best`` score so far, and no worse than
    the starting weights' score ``start`` (adaptation never writes weights that the tail
    scores below the ones it started from)."""
    return value <= best * (1.0 + tolerance) and value <= start


def _train_mode(model: torch.nn.Module, freeze_norm: bool) -> None:
    """Training mode, with the BatchNorm layers left in eval mode when ``freeze_norm``."""
    model.train()
    if freeze_norm:
        for module in model.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.eval()


def _prefixed(scores: dict) -> dict:
    return {f"holdout_{k}": v for k, v in scores.items()}


class _Bar:
    """A rich progress bar, one task per stage (or nothing)."""

    def __init__(self, enabled: bool):
        self.progress = None
        self.task = None
        if enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TextColumn("{task.fields[loss]}"), TimeElapsedColumn())
            self.progress.start()

    def stage(self, name: str, total: int) -> None:
        if self.progress is not None:
            self.task = self.progress.add_task(name, total=total, loss="")

    def advance(self, loss: float | None = None) -> None:
        if self.progress is not None and self.task is not None:
            self.progress.update(self.task, advance=1, loss="" if loss is None else f"loss {loss:.4f}")

    def stop(self) -> None:
        if self.progress is not None:
            self.progress.stop()
