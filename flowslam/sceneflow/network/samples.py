"""Multi-frame samples for the scene-flow network, for training and for inference.

A sample for newest scan ``k`` holds ``T`` frames ``k-T+1 .. k`` (oldest first), each
moved into the sensor frame of scan ``k`` with an *ego prior* ``T_k_j`` (maps scan j
into scan k). The source is scan ``k-1``: the network predicts its residual flow on
top of the prior, so that ``T_k_{k-1} p + residual = p + flow`` (flow in the
Argoverse 2 convention, metres, sensor frame k).

- Inference (``frames_to_sample``): the prior comes from the system's own estimates
  (previous odometry, constant velocity for the newest step). GT is never used.
- Training (``training_sample``): the prior is the GT relative pose *deliberately
  corrupted* (``PriorNoise``: up to ~1.5 m and 5 deg yaw on the newest step, small
  drift on older ones, and sometimes no prior at all), so that the network learns
  to output the full flow under an imperfect prior -- which is what makes its flow
  usable as odometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from flowslam import geometry
from flowslam.config.training import PriorNoise
from flowslam.frame import Dataset, Frame


@dataclass
class Sample:
    """Network input and (for training) targets. Arrays are float32 unless noted.

    ``points``: T arrays (N_t,3), newest sensor frame, oldest first; ``points[-2]`` is
    the compensated source. ``source_points``: (N,3) the source points in their own
    sensor frame (k-1). ``T_new_src``: the prior ``T_{k,k-1}`` (4x4 float64).
    ``residual``/``dynamic``/``gt_flow``: targets for the source points (training).
    ``source_index``: (N,) int, row of each source point in the source scan.
    """

    points: list[np.ndarray]
    source_points: np.ndarray
    T_new_src: np.ndarray
    source_index: np.ndarray
    residual: np.ndarray | None = None
    dynamic: np.ndarray | None = None
    gt_flow: np.ndarray | None = None
    classes: np.ndarray | None = None


def transform_points_torch(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """(N,3) points of frame b mapped into frame a (float64, m), computed with torch.

    The same map as ``geometry.transform_points`` (equal to ~1e-15 m). For whole scans
    it avoids NumPy's OpenBLAS, whose threads busy-wait: on the loaded 2-core machine
    a 124k-point transform took 48 ms there (3 ms with ``OPENBLAS_NUM_THREADS=1``),
    1.6 ms with torch (which honours ``OMP_WAIT_POLICY``).
    """
    import torch

    p = torch.from_numpy(np.ascontiguousarray(points_b, dtype=np.float64))
    T = torch.from_numpy(np.asarray(T_a_b, dtype=np.float64))
    return torch.addmm(T[:3, 3], p, T[:3, :3].T).numpy()


def _subsample(n: int, max_points: int | None, rng: np.random.Generator | None) -> np.ndarray:
    if max_points is None or n <= max_points:
        return np.arange(n)
    if rng is None:  # deterministic, evenly spread (inference)
        return np.linspace(0, n - 1, max_points).astype(np.int64)
    return np.sort(rng.choice(n, size=max_points, replace=False))


def frames_to_sample(
    frames: list[Frame],
    T_new_old: list[np.ndarray],
    max_points: int | None = None,
    rng: np.random.Generator | None = None,
) -> Sample:
    """Build a sample from T frames (oldest first) and priors ``T_new_old[t]`` (maps frame t
    into the newest frame; the last one is the identity). No GT is read."""
    if len(frames) != len(T_new_old) or len(frames) < 2:
        raise ValueError("need >= 2 frames and one prior per frame")
    points = []
    source_index = None
    for t, (frame, T) in enumerate(zip(frames, T_new_old)):
        idx = _subsample(len(frame.points), max_points, rng)
        if t == len(frames) - 2:
            source_index = idx
        points.append(geometry.transform_points(T, frame.points[idx]).astype(np.float32))
    source = frames[-2]
    return Sample(
        points=points,
        source_points=source.points[source_index].astype(np.float32),
        T_new_src=np.asarray(T_new_old[-2], dtype=np.float64),
        source_index=source_index,
    )


def _perturbation(noise: PriorNoise, scale: float, rng: np.random.Generator) -> np.ndarray:
    r = noise.max_translation_m * scale * np.sqrt(rng.uniform())
    phi = rng.uniform(0, 2 * np.pi)
    t = [r * np.cos(phi), r * np.sin(phi), rng.uniform(-1, 1) * noise.max_z_m * scale]
    rp = noise.max_roll_pitch_deg * scale
    angles = [rng.uniform(-rp, rp), rng.uniform(-rp, rp), rng.uniform(-1, 1) * noise.max_yaw_deg * scale]
    return geometry.from_euler("xyz", angles, t=t, degrees=True)


def noisy_priors(gt_poses: np.ndarray, noise: PriorNoise, rng: np.random.Generator) -> list[np.ndarray]:
    """Corrupted ``T_new_old`` for T GT poses ``T_world_sensor`` (oldest first).

    The newest step ``T_{k,k-1}`` gets a full-size error (a wrong constant-velocity
    guess); each older step a small one (odometry drift); sometimes all identity.
    """
    n = len(gt_poses)
    if rng.uniform() < noise.p_no_prior:
        return [np.eye(4) for _ in range(n)]
    steps = [geometry.relative(gt_poses[t + 1], gt_poses[t]) for t in range(n - 1)]  # T_{t+1,t}
    size = rng.uniform() ** noise.scale_exponent if noise.scale_exponent > 0 else 1.0
    priors = [np.eye(4)]
    T = np.eye(4)
    for t in range(n - 2, -1, -1):
        scale = size * (1.0 if t == n - 2 else noise.older_step_fraction)
        T = T @ (_perturbation(noise, scale, rng) @ steps[t])
        priors.append(T.copy())
    return priors[::-1]


def training_sample(
    dataset: Dataset,
    newest: int,
    num_frames: int,
    noise: PriorNoise,
    rng: np.random.Generator,
    max_points: int | None = 32768,
) -> Sample:
    """A training sample whose newest scan is ``newest`` (needs GT poses and the source's GT flow)."""
    first = newest - num_frames + 1
    if first < 0:
        raise ValueError(f"sample needs frames {first}..{newest}")
    frames = [dataset[i] for i in range(first, newest + 1)]
    source = frames[-2]
    if source.gt_flow is None or any(f.gt_pose is None for f in frames):
        raise ValueError(f"frame {source.index} of {dataset.path} has no GT flow or poses")
    gt_poses = np.stack([f.gt_pose for f in frames])
    sample = frames_to_sample(frames, noisy_priors(gt_poses, noise, rng), max_points, rng)
    idx = sample.source_index
    flow = source.gt_flow[idx]
    target = source.points[idx] + flow  # same physical points at k, sensor frame k
    compensated = geometry.transform_points(sample.T_new_src, source.points[idx])
    sample.residual = (target - compensated).astype(np.float32)
    sample.gt_flow = flow.astype(np.float32)
    sample.dynamic = (
        np.zeros(len(idx), bool) if source.gt_dynamic is None else source.gt_dynamic[idx].astype(bool)
    )
    sample.classes = None if source.gt_class is None else source.gt_class[idx]
    return sample


def training_indices(dataset: Dataset, num_frames: int) -> list[int]:
    """Newest-scan indices that make a complete sample (the source needs flow to the newest)."""
    return list(range(num_frames - 1, len(dataset)))
