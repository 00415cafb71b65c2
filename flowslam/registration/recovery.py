"""Motion faults: find a step that its own evidence does not support, and judge which of
two solutions the scans explain better.

A registration started from the constant-velocity prior can converge far from the
truth when the motion changes abruptly (a sharp turn at a low frame rate). Ground truth
is never used here. What shows a faulty step is the registration's own evidence:

- **cues** (:class:`MotionFaultDetector`, from numbers the frontend has anyway, so
  checking costs nothing): the measurement fell back to constant velocity; the static
  refinement was rejected; its fitness dropped well below that of the last good steps;
  the network called much more of the scan dynamic than on the last good steps (a wrong
  ego prior makes static structure look moving); the result differs from the prior by
  more than a plausible change of motion; before the relative cues have a history, the
  refinement's fitness is below an absolute floor; the step is the sequence's first,
  whose prior is no measurement (``check_first_step``);
- **evidence** (:class:`AlignmentEvidence`, computed only for a faulty step): the share
  of scan k's points that land on scan k-1 under a candidate ``T_prev_curr``; the same
  measure on the same points judges the first solution and the re-initialised one;
- **a global start** (:func:`global_start`): FPFH + RANSAC (+ ICP) of scan k onto scan
  k-1 (:mod:`flowslam.registration.global_registration`), which needs no prior; where it
  lands on a first step's own solution it confirms it, and nothing is re-run.

Frames: ``T_prev_curr`` maps scan k into sensor frame k-1 (4x4, m); angles in radians.
The options are :class:`flowslam.config.ssf.MotionRecoveryConfig`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from flowslam import geometry
from flowslam.config.ssf import MotionRecoveryConfig

__all__ = ["AlignmentEvidence", "MotionFaultDetector", "StepEvidence", "global_start", "prior_disagreement"]

#: Fault cues and what they mean (the keys ``run.json`` counts them under).
FAULT_CUES = {
    "fallback": "the measurement fell back to the constant-velocity prediction",
    "refine_rejected": "the static refinement found too few partners on scan k",
    "fitness_drop": "the refinement's fitness fell well below that of the last good steps",
    "dynamic_jump": "the network called much more of the scan dynamic than on the last good steps",
    "prior_disagreement": "the measurement is far from the constant-velocity prior",
    "first_step": "the first step of the sequence, whose prior is no measurement (always checked)",
    "early_low_fitness": "the refinement's fitness is low while the relative cues have no history yet",
}


@dataclass
class StepEvidence:
    """What a step's own registration says about it (no ground truth)."""

    fallback: bool
    """The measurement is the constant-velocity prediction."""
    refine_accepted: bool | None = None
    """The static refinement was accepted (None: it did not run)."""
    refine_fitness: float | None = None
    """Share of the refinement's source points with a partner on scan k."""
    dynamic_share: float | None = None
    """Share of scan k-1's points the network called dynamic."""
    prior_rotation_rad: float = 0.0
    """Rotation between the constant-velocity prior and the measurement."""
    prior_translation_m: float = 0.0
    """Translation between the constant-velocity prior and the measurement."""


def prior_disagreement(T_prior: np.ndarray, T_prev_curr: np.ndarray) -> tuple[float, float]:
    """(rotation rad, translation m) of ``inv(T_prior) @ T_prev_curr``: how far the
    measurement lies from the prior (both ``T_prev_curr``, scan k into frame k-1)."""
    E = geometry.inv(T_prior) @ T_prev_curr
    return float(geometry.rotation_angle(E)), float(np.linalg.norm(E[:3, 3]))


class MotionFaultDetector:
    """The cues of the module doc; the relative ones compare with the medians of the last
    ``history`` good steps (those :meth:`remember` was given) once there are ``min_history``;
    ``first_step`` (with ``check_first_step``) fires on the first step checked."""

    def __init__(self, config: MotionRecoveryConfig | None = None):
        self.config = c = config or MotionRecoveryConfig()
        self._fitness: deque[float] = deque(maxlen=c.history)
        self._dynamic: deque[float] = deque(maxlen=c.history)
        self._first = True  # no step checked yet

    def check(self, e: StepEvidence) -> list[str]:
        """The cues (keys of :data:`FAULT_CUES`) that fire for ``e``, the next step of the
        sequence; empty: a good step."""
        c = self.config
        first, self._first = self._first, False
        fired = {
            "fallback": e.fallback,
            "refine_rejected": e.refine_accepted is False,
            "fitness_drop": e.refine_accepted is True and self._median_times(self._fitness, c.fitness_drop,
                                                                              e.refine_fitness, below=True),
            "dynamic_jump": self._median_times(self._dynamic, c.dynamic_jump, e.dynamic_share, below=False)
            and e.dynamic_share > c.dynamic_share_floor,
            "prior_disagreement": e.prior_rotation_rad > np.deg2rad(c.max_prior_rotation_deg)
            or e.prior_translation_m > c.max_prior_translation_m,
            "first_step": first and c.check_first_step,
            "early_low_fitness": e.refine_accepted is True and e.refine_fitness is not None
            and len(self._fitness) < c.min_history and e.refine_fitness < c.early_min_fitness,
        }
        return [cue for cue, on in fired.items() if on]

    def remember(self, e: StepEvidence) -> None:
        """A good step (or one the re-initialisation recovered or confirmed) joins the
        history of the relative cues."""
        if e.refine_accepted and e.refine_fitness is not None:
            self._fitness.append(e.refine_fitness)
        if e.dynamic_share is not None:
            self._dynamic.append(e.dynamic_share)

    def _median_times(self, history: deque, ratio: float, value: float | None, below: bool) -> bool:
        """``value`` below (or above) ``ratio`` times the median of ``history``; False while
        the history is shorter than ``min_history`` or there is no value."""
        if value is None or len(history) < self.config.min_history:
            return False
        limit = ratio * float(np.median(history))
        return value < limit if below else value > limit


class AlignmentEvidence:
    """How well a ``T_prev_curr`` explains a scan pair: the share of scan k's points
    (voxel-downsampled, within ``max_range_m``) whose image in frame k-1 has a scan k-1
    point within ``distance_m``. Built once per pair (KD-tree of scan k-1), then cheap
    per candidate; the same points judge every candidate."""

    def __init__(self, points_curr: np.ndarray, points_prev: np.ndarray, voxel_m: float, distance_m: float,
                 max_range_m: float):
        from scipy.spatial import cKDTree

        self.source = _downsample(points_curr, voxel_m, max_range_m)
        self.tree = cKDTree(_downsample(points_prev, voxel_m, max_range_m))
        self.distance_m = distance_m

    def __call__(self, T_prev_curr: np.ndarray) -> float:
        if len(self.source) == 0 or self.tree.n == 0:
            return 0.0
        d, _ = self.tree.query(geometry.transform_points(T_prev_curr, self.source),
                               distance_upper_bound=self.distance_m)
        return float(np.isfinite(d).mean())


def _downsample(points: np.ndarray, voxel_m: float, max_range_m: float) -> np.ndarray:
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    p = p[np.einsum("ij,ij->i", p, p) < max_range_m**2]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(voxel_m)
    return np.asarray(cloud.points)


def global_start(curr, prev, registration, min_fitness: float) -> tuple[np.ndarray | None, dict]:
    """``T_prev_curr`` of scan k (``curr``) onto scan k-1 (``prev``) from FPFH + RANSAC
    (+ ICP), both :class:`~flowslam.registration.global_registration.ScanFeatures` of
    ``registration`` (a :class:`~flowslam.registration.global_registration.FpfhRansac`);
    None when either scan has too few points or RANSAC's fitness is below ``min_fitness``.
    Also the alignment's stats (``fitness``, ..., ``stage_ms``)."""
    if curr.features is None or prev.features is None:
        return None, {"reason": "too few points for features"}
    aligned = registration.align(curr, prev)
    stats = dict(aligned.stats, stage_ms=aligned.laps)
    if aligned.stats["fitness"] < min_fitness:
        return None, dict(stats, reason=f"RANSAC fitness {aligned.stats['fitness']:.2f} < {min_fitness}")
    return aligned.T_target_source, stats
