"""Options of training the scene-flow network (``training:`` in the run config, the
``flowslam train --config`` file). Metres, seconds, degrees where the name says so.

The network's own size knobs (``ModelConfig``) travel with its weights and live with
the network (``flowslam.sceneflow.network.model``); a training run names them by
``model_preset`` and ``model_overrides``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from flowslam.config.base import StrictModel


class PriorNoise(StrictModel):
    """How the training ego prior is corrupted (uniform draws; metres and degrees)."""

    max_translation_m: float = Field(1.5, ge=0)
    """Newest step: translation error drawn uniformly in a disc of this radius (x, y)."""
    max_yaw_deg: float = Field(5.0, ge=0)
    """Newest step: yaw error drawn uniformly in +-this."""
    max_z_m: float = Field(0.1, ge=0)
    """Newest step: vertical error drawn uniformly in +-this."""
    max_roll_pitch_deg: float = Field(0.5, ge=0)
    """Newest step: roll and pitch errors drawn uniformly in +-this."""
    older_step_fraction: float = Field(0.1, ge=0)
    """Older steps (odometry already estimated) get errors scaled by this."""
    p_no_prior: float = Field(0.1, ge=0, le=1)
    """Probability of feeding the raw scans (identity prior)."""
    scale_exponent: float = Field(0.0, ge=0)
    """Per sample, every error above is multiplied by ``u ** scale_exponent`` with ``u``
    uniform in [0, 1]: 0 keeps the full-size errors, 2 draws a third of the size on
    average, so that the network also learns to be precise when the prior is nearly
    right (as it is in a second pass or on smooth driving)."""


class TrainConfig(StrictModel):
    """Every knob of a training run."""

    data: list[Path] = Field(default_factory=list)
    """Training sequences (simulated, or Argoverse-2-format logs with flow labels)."""
    val: list[Path] = Field(default_factory=list)
    """Validation sequences (held out)."""
    out_dir: Path = Path("runs/sceneflow")
    """Checkpoints and ``history.json`` go here."""
    model_preset: str = "tiny"
    """Network size: 'tiny' (CPU) or 'full' (GPU)."""
    model_overrides: dict = Field(default_factory=dict)
    """Fields of the network's ``ModelConfig`` that replace the preset's."""
    init_weights: Path | None = None
    """Start from these weights (a weights file or a checkpoint) instead of random ones;
    the model config must match. Unlike ``resume``, optimiser and schedule start fresh."""
    num_frames: int = Field(5, ge=2)
    """Frames per sample, oldest first."""
    max_points: int = Field(16384, ge=16)
    """Points sampled per frame (the network sees at most this many)."""
    epochs: int = Field(10, ge=1)
    """OneCycle schedule length in epochs."""
    batch_size: int = Field(2, ge=1)
    """Samples per optimiser step (per process)."""
    lr: float = Field(2e-3, gt=0)
    """Peak learning rate of the OneCycle schedule."""
    weight_decay: float = Field(1e-4, ge=0)
    """AdamW weight decay."""
    loss: Literal["scene-adaptive", "deflow"] = "scene-adaptive"
    """Flow loss: MambaFlow's scene-adaptive loss or DeFlow's speed-bucketed loss."""
    bce_weight: float = Field(0.2, ge=0)
    """Weight of the dynamic-segmentation binary cross-entropy."""
    prior_noise: PriorNoise = PriorNoise()
    """Corruption of the ego prior during training."""
    seed: int = 0
    """Seed of sampling, priors and initialisation."""
    max_minutes: float | None = Field(None, gt=0)
    """Stop (after a checkpoint) once this much wall time has passed."""
    val_samples: int = Field(24, ge=1)
    """Validation samples per epoch (fixed, seeded priors)."""
    num_workers: int = Field(0, ge=0)
    """DataLoader worker processes building the samples (0: in the training process). A
    sample depends only on its seed, epoch and index, so the batches are the same for any
    number of workers; on a GPU the workers keep it fed."""
    amp: bool = True
    """bf16 autocast on CUDA (ignored on CPU)."""
    num_threads: int | None = Field(None, ge=1)
    """torch intra-op threads on CPU (None: torch's default)."""
