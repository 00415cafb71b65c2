"""Options of self-supervised adaptation (``adapt:`` in the run config, ``flowslam adapt``).

The network is fine-tuned on the user's own unlabelled sequences against the ``ssf``
pipeline's refined output (the teacher, run with the config's ``ssf:`` section) and
the self-supervised losses of ``flowslam.sceneflow.network.self_supervised``. Metres,
seconds, degrees where the name says so.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from flowslam.config.base import StrictModel
from flowslam.config.training import PriorNoise


class AdaptLossWeights(StrictModel):
    """Weight of each term of the adaptation loss (0 switches a term off)."""

    distill: float = Field(1.0, ge=0)
    """The teacher's refined flow (scene-adaptive loss on the residual flow)."""
    distill_bce: float = Field(0.2, ge=0)
    """The teacher's dynamic labels (binary cross-entropy of the dynamic logit), inside ``distill``."""
    max_pos_weight: float = Field(10.0, ge=1)
    """The BCE weighs the rare dynamic points up to this much (negatives / positives)."""
    calibrated_bce: bool = False
    """The BCE's logit is shifted by the log of that weight (logit adjustment), so the
    adapted head's probabilities stay calibrated like the shipped head's (trained with a
    plain BCE) and the pipeline's ``dynamic_threshold`` means the same for both. Opt-in.
    Measured (stop 56, ``python tools/bench_adapt.py sim --set adapt.loss.calibrated_bce=true``):
    network-only Dynamic IoU on `dt` 299 0.413 -> 0.549 and on fresh 651 0.299 -> 0.365; but the
    epoch it wrote (4, against 8 without it) ran the network alone at EPE3D 0.081 / 0.093 m
    against 0.060 / 0.077 (docs/sceneflow_evaluation.md, stop 56)."""
    data: float = Field(0.2, ge=0)
    """Truncated nearest-neighbour distance of the warped source to scan k."""
    motion: float = Field(0.2, ge=0)
    """L_mot: each segment of the teacher's segmentation moves rigidly."""
    consistency: float = Field(0.1, ge=0)
    """L_SC: dynamic probability and departure from the ego motion agree."""
    rigid_chamfer: float = Field(0.2, ge=0)
    """L_CD: the source moved segment by segment lands on scan k."""


class AdaptConfig(StrictModel):
    """Every knob of ``flowslam adapt``."""

    out_dir: Path = Path("runs/adapt")
    """Teacher cache, checkpoints, ``history.json`` and ``report.json`` go here."""
    cache_dir: Path | None = None
    """Where the teacher's cache lives instead of ``out_dir/cache``: adapt runs that share
    it compute the teacher of a sequence once (a run over fewer frames of it reads the
    cached prefix)."""
    holdout_fraction: float = Field(0.2, gt=0, lt=1)
    """The last fraction of each sequence's frames (at least 2) is never trained on: it
    stops the adaptation early and the report compares the models there."""
    epochs: int = Field(8, ge=1)
    """Passes over the training pairs (OneCycle schedule length)."""
    patience: int = Field(4, ge=1)
    """Stop when the held-out score has not improved for this many epochs."""
    select_tolerance: float = Field(0.01, ge=0)
    """The weights written are those of the latest epoch whose held-out score is within
    this fraction of the best one: a tail of a few pairs cannot tell such epochs apart,
    and the later one has had more of the schedule."""
    lr: float = Field(2e-4, gt=0)
    """Peak learning rate (OneCycle)."""
    weight_decay: float = Field(1e-4, ge=0)
    """AdamW weight decay."""
    batch_size: int = Field(1, ge=1)
    """Pairs per optimiser step."""
    max_points: int | None = Field(None, ge=16)
    """Points sampled per frame; None: the run config's ``ssf.network.max_points``."""
    freeze_norm: bool = True
    """Keep the BatchNorm statistics of the starting weights (their affine parameters
    still learn): a batch of one or two scans is too small to re-estimate them."""
    loss: AdaptLossWeights = AdaptLossWeights()
    """Weights of the loss terms."""
    truncate_m: float = Field(2.0, gt=0)
    """Nearest-neighbour distances are capped here (data term, L_CD)."""
    consistency_threshold_m: float = Field(0.1, gt=0)
    """L_SC: a departure from the ego motion above this (m per frame) means dynamic."""
    min_segment_points: int = Field(10, ge=3)
    """Segments with fewer points are left out of L_mot and L_CD."""
    prior_noise: PriorNoise = PriorNoise(
        max_translation_m=0.3, max_yaw_deg=1.0, max_z_m=0.05, max_roll_pitch_deg=0.2, older_step_fraction=0.1,
        p_no_prior=0.0, scale_exponent=1.0,
    )
    """Extra errors put on the system's own ego priors (augmentation): full size on the
    constant-velocity guess of the newest scan, ``older_step_fraction`` of it on each
    older step."""
    seed: int = 0
    """Sampling, augmentation and shuffling seed."""
    report_refined: bool = True
    """The final report also runs both weights in the whole default ``ssf`` frontend over
    the held-out frames (its accuracy and what it spends per pair: objects-stage time,
    candidates); False: network only (faster)."""
    max_minutes: float | None = Field(None, gt=0)
    """Stop (after a checkpoint) once this much wall time has passed, teacher included."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where the network trains: 'auto' is CUDA when present, else the CPU."""
    num_threads: int | None = Field(None, ge=1)
    """torch intra-op threads on CPU (None: torch's default)."""
