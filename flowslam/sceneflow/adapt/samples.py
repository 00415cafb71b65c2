"""Samples of ``flowslam adapt``: the network's input for a pair, built exactly as the
``ssf`` frontend builds it at inference, with the teacher's targets.

The T scans ``k-T+1 .. k`` (the first scan of the run repeated at its start, as
inference does) are moved into scan k's sensor frame with the system's *own* pose
estimates (the teacher's chained odometry) and a constant-velocity guess of scan k,
optionally with extra random errors (augmentation: a network-only run's own poses
are less accurate than the teacher's). No ground truth is read. Lengths in metres, flows in metres per frame, sensor frame k unless noted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowslam import geometry
from flowslam.config.training import PriorNoise
from flowslam.frame import Dataset
from flowslam.sceneflow.adapt.teacher import Teacher, ego_flow
from flowslam.sceneflow.network.samples import Sample, frames_to_sample, noisy_priors


@dataclass
class AdaptSample:
    """One pair's network input and self-supervised targets (arrays float32 unless noted)."""

    sample: Sample
    """The network input; ``sample.residual`` / ``sample.dynamic`` hold the teacher's
    residual flow and dynamic labels of the sampled source points."""
    teacher_flow: np.ndarray
    """(N,3) the teacher's flow of the sampled source points (AV2 convention)."""
    ego_flow: np.ndarray
    """(N,3) the static world's flow under the teacher's step, same points."""
    segments: np.ndarray
    """(N,) int64 rigid parts: 0 static, 1.. instances, -1 none (``TeacherPair.segments``)."""
    target: np.ndarray
    """(M,3) every point of scan k (its sensor frame): the data term's target."""
    index: int
    """Dataset index of scan k."""


def window(frames: list[int], k: int, num_frames: int) -> list[int]:
    """The dataset indices of the network's T input scans for newest scan ``k`` (oldest
    first): the scans before ``k`` in the run, the first one repeated at the start."""
    pos = frames.index(k)
    return [frames[max(0, pos - num_frames + 1 + t)] for t in range(num_frames)]


def own_poses(teacher: Teacher, indices: list[int]) -> np.ndarray:
    """(T,4,4) ``T_world_sensor`` of the input scans from the teacher's own estimates, the
    newest one guessed at constant velocity (the last step repeated), as the frontend does."""
    k = indices[-1]
    pos = teacher.frames.index(k)
    prev = teacher.frames[pos - 1]
    step = (geometry.relative(teacher.poses[teacher.frames[pos - 2]], teacher.poses[prev])
            if pos >= 2 else np.eye(4))
    return np.stack([teacher.poses[i] for i in indices[:-1]] + [teacher.poses[prev] @ step])


def own_priors(teacher: Teacher, indices: list[int]) -> list[np.ndarray]:
    """``T_new_old`` of each input scan from :func:`own_poses` (the inference priors)."""
    poses = own_poses(teacher, indices)
    T_new_world = geometry.inv(poses[-1])
    return [T_new_world @ P for P in poses[:-1]] + [np.eye(4)]


def adapt_sample(dataset: Dataset, teacher: Teacher, k: int, num_frames: int, max_points: int | None,
                 noise: PriorNoise | None = None, rng: np.random.Generator | None = None) -> AdaptSample:
    """The sample whose newest scan is ``k`` (``k`` must not be the teacher's first frame).

    With ``rng`` the points are sampled at random and, with ``noise``, the priors get the
    training errors of ``noisy_priors`` on top of the own poses (a full-size error on the
    constant-velocity guess, small ones on the older steps: the drift of a less accurate
    odometry); without, the points are spread evenly and the priors are those of inference.
    """
    indices = window(teacher.frames, k, num_frames)
    if noise is not None and rng is not None:
        priors = noisy_priors(own_poses(teacher, indices), noise, rng)
    else:
        priors = own_priors(teacher, indices)
    scans = [dataset[i] for i in indices]
    sample = frames_to_sample(scans, priors, max_points, rng)
    pair = teacher.pairs[k]
    idx = sample.source_index
    src = scans[-2].points[idx]
    compensated = geometry.transform_points(sample.T_new_src, src)
    flow = pair.flow[idx].astype(np.float64)
    sample.residual = (src + flow - compensated).astype(np.float32)
    sample.dynamic = ~pair.static[idx]
    return AdaptSample(
        sample=sample, teacher_flow=flow.astype(np.float32), ego_flow=ego_flow(pair, src).astype(np.float32),
        segments=pair.segments[idx], target=np.asarray(scans[-1].points, np.float32), index=k,
    )
