"""The two plug-in contracts of the pipeline: ``Frontend`` and ``Backend``.

Data flow per scan ``k`` (see ``flowslam.pipeline``)::

    frame_k --Frontend.process--> FrontendOutput(T_prev_curr, covariance, per-point outputs)
            --Backend.add_odometry--> trajectory (T_world_sensor for every scan so far)

Frames and units
----------------
- ``T_prev_curr`` maps points of scan ``k`` into the sensor frame of scan ``k-1``
  (4x4 float64, metres). It is ``inv(T_world_{k-1}) @ T_world_k``; the scene-flow
  ``T_{t+1,t}`` of the Argoverse 2 convention is its inverse.
- ``covariance`` is 6x6 in GTSAM's Pose3 tangent of ``T_prev_curr``
  (rotation rad first, then translation m; right perturbation ``T * Exp(xi)``).
- Per-point outputs, where a frontend has them, refer to the points of the
  *previous* scan ``k-1`` (``points``, sensor frame ``k-1``): ``flow`` (N,3) in
  the Argoverse 2 convention (``points + flow`` = the same physical point in
  sensor frame ``k``), ``static_mask`` (N,) bool, ``instance_ids`` (N,) int (-1 none).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from flowslam.frame import Frame


@dataclass
class FrontendOutput:
    """What a frontend says about scan ``index`` (see module doc for frames)."""

    index: int
    T_prev_curr: np.ndarray | None
    """None for the first scan (nothing to be relative to)."""
    covariance: np.ndarray | None = None
    points: np.ndarray | None = None
    flow: np.ndarray | None = None
    static_mask: np.ndarray | None = None
    instance_ids: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    """Free-form per-frame diagnostics (iterations, inliers, fallbacks, ...)."""


@runtime_checkable
class Frontend(Protocol):
    """Estimates the motion between consecutive scans (and per-point outputs if it can)."""

    name: str
    # Optional: ``config_sections`` (tuple of str), the config sections the frontend
    # reads; ``flowslam run`` refuses a command-line option of another section.
    # Optional: ``upcoming(frame)``, told the next scan before ``process`` gets the current
    # one (the run loop reads one scan ahead), so work on it may start early.

    def process(self, frame: Frame) -> FrontendOutput:
        """Consume the next scan in order; return the relative motion to the previous one."""
        ...


@runtime_checkable
class Backend(Protocol):
    """Turns odometry (and loop) measurements into the current trajectory estimate."""

    name: str

    def add_odometry(
        self, index: int, T_prev_curr: np.ndarray | None, covariance: np.ndarray | None
    ) -> None:
        """Add scan ``index``; ``T_prev_curr`` is None for the first scan (anchored at identity)."""
        ...

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, covariance: np.ndarray) -> None:
        """Add a constraint ``T_i_j`` (maps scan j into scan i) between two earlier scans."""
        ...

    def trajectory(self) -> np.ndarray:
        """Current estimate: (K,4,4) ``T_world_sensor`` for every scan added so far."""
        ...

    def latest_pose(self) -> np.ndarray:
        """Current estimate of the last scan's ``T_world_sensor`` (cheap: called every scan)."""
        ...


@dataclass
class LoopClosure:
    """A verified loop constraint between an earlier scan ``i`` and the current scan ``j``.

    ``T_i_j`` maps points of scan j into sensor frame i (4x4, m); ``covariance`` is
    6x6 in the Pose3 tangent of ``T_i_j`` ([rot rad, trans m]).
    """

    i: int
    j: int
    T_i_j: np.ndarray
    covariance: np.ndarray
    fitness: float = float("nan")
    """Share of scan j's points with a neighbour in scan i after alignment (0..1)."""
    inlier_rmse: float = float("nan")
    """RMSE of the aligned correspondences (m)."""
    descriptor_distance: float = float("nan")
    info: dict = field(default_factory=dict)


@runtime_checkable
class LoopCloser(Protocol):
    """Finds and verifies loops; the pipeline passes every accepted one to the backend."""

    def add_scan(self, index: int, points: np.ndarray, T_world_sensor: np.ndarray) -> list[LoopClosure]:
        """Add scan ``index`` (points (N,3) in its sensor frame, its current pose estimate)
        and return the loops it closes with earlier scans (possibly none)."""
        ...
