"""Frontends ``gt`` and ``gt-flow``: odometry from the dataset's ground-truth scene flow.

Ablation upper bounds, and the tool for testing the backend with known-good odometry:

- ``gt``: GT flow of the static points only (``Frame.gt_dynamic`` labels remove the
  moving ones), instance ids from ``Frame.gt_instance``;
- ``gt-flow``: GT flow of *all* points, no segmentation: the robust registration of
  :class:`flowslam.flow_odometry.FlowToPose` must reject the moving points itself.
  ``static_mask`` is then ``None`` (a map built from it keeps moving objects).

Frames (see :mod:`flowslam.interfaces`): at scan ``k`` the frontend uses the *previous*
frame ``k-1``: its points (sensor frame ``k-1``) and its ``gt_flow`` (Argoverse 2
convention, into sensor frame ``k``), so the last frame of a sequence needs no flow.
The returned ``FrontendOutput`` carries ``T_prev_curr`` (scan k into frame k-1) with its
covariance and the per-point outputs of scan ``k-1``.

Only datasets with flow labels qualify (the simulator's sequences, Argoverse 2 logs
with ``flow_labels``). If the first frame pair has no GT flow the frontend raises
``InputError``; a later frame without flow in a dataset that had flow before gives the
constant-velocity fallback (counted in ``stats``), not an error.
"""

from __future__ import annotations

import numpy as np

from flowslam.frame import Frame
from flowslam.errors import InputError
from flowslam.config import FlowOdometryConfig
from flowslam.flow_odometry import FlowToPose
from flowslam.interfaces import FrontendOutput

__all__ = ["GroundTruthFlowFrontend", "exact_flow_options", "make_gt_frontend", "make_gt_flow_frontend", "NO_FLOW_MESSAGE"]

NO_FLOW_MESSAGE = (
    "has no ground-truth flow; the gt/gt-flow frontends need a dataset with flow labels "
    "(simulated sequences, Argoverse 2 with flow_labels)"
)


EXACT_FLOOR_FACTOR = 0.1
"""The covariance floor of ``flow_odometry`` stands for model errors that GT flow does not
have (timing, deskew, calibration): the GT frontends use this share of its sigmas (not
less: Argoverse 2's flow labels are exact only to their float16 rounding, ~0.8 mm)."""


def exact_flow_options(options: FlowOdometryConfig) -> FlowOdometryConfig:
    """``options`` with the covariance floor for exact (GT) flow, whose steps are exact to
    a millimetre or better, so that a map factor or a loop does not pull them (floor
    0.01 deg / 5 mm -> 0.001 deg / 0.5 mm with the defaults)."""
    return options.model_copy(update={
        "min_rotation_std_deg": options.min_rotation_std_deg * EXACT_FLOOR_FACTOR,
        "min_translation_std_m": options.min_translation_std_m * EXACT_FLOOR_FACTOR,
    })


class GroundTruthFlowFrontend:
    """``gt`` (``use_labels=True``) or ``gt-flow`` (``use_labels=False``), see module doc."""

    config_sections = ("flow_odometry",)
    """The config sections it reads (an option of another section given on the command line is an error)."""

    def __init__(self, use_labels: bool, options: FlowOdometryConfig | None = None):
        self.use_labels = use_labels
        self.name = "gt" if use_labels else "gt-flow"
        self.odometry = FlowToPose(exact_flow_options(options or FlowOdometryConfig()))
        self._prev: Frame | None = None
        self._seen_flow = False

    def _labels_of(self, prev: Frame) -> str | None:
        """None if ``prev`` has what this frontend needs, else the problem (raises if the
        dataset is inconsistent: flow without dynamic labels for ``gt``)."""
        if prev.gt_flow is None:
            return NO_FLOW_MESSAGE
        if self.use_labels and prev.gt_dynamic is None:
            raise InputError(
                prev.where,
                "has ground-truth flow but no dynamic labels; the gt frontend needs both "
                "(use --frontend gt-flow for flow alone)",
            )
        return None

    def process(self, frame: Frame) -> FrontendOutput:
        prev, self._prev = self._prev, frame
        if prev is None:
            return FrontendOutput(index=frame.index, T_prev_curr=None, stats={"fallback": False, "reason": None})
        dt = float(frame.timestamp - prev.timestamp)
        dt = dt if dt > 0 else None

        problem = self._labels_of(prev)
        if problem is not None:
            if not self._seen_flow:
                raise InputError(prev.where, problem)
            est = self.odometry.fallback("no_flow", f"frame {prev.index} {problem.split(';')[0]}", len(prev.points), dt)
            return FrontendOutput(
                index=frame.index, T_prev_curr=est.T_prev_curr, covariance=est.covariance, stats=est.stats
            )
        self._seen_flow = True

        static_mask = ~np.asarray(prev.gt_dynamic, dtype=bool) if self.use_labels else None
        est = self.odometry.estimate(prev.points, prev.gt_flow, static_mask=static_mask, dt=dt)
        return FrontendOutput(
            index=frame.index,
            T_prev_curr=est.T_prev_curr,
            covariance=est.covariance,
            points=prev.points,
            flow=prev.gt_flow,
            static_mask=static_mask,
            instance_ids=prev.gt_instance if self.use_labels else None,
            stats=est.stats,
        )


def _options(config) -> FlowOdometryConfig:
    return getattr(config, "flow_odometry", None) or FlowOdometryConfig()


def make_gt_frontend(config) -> GroundTruthFlowFrontend:
    """Factory of ``gt`` (GT flow + GT dynamic labels)."""
    return GroundTruthFlowFrontend(use_labels=True, options=_options(config))


def make_gt_flow_frontend(config) -> GroundTruthFlowFrontend:
    """Factory of ``gt-flow`` (GT flow, no segmentation)."""
    return GroundTruthFlowFrontend(use_labels=False, options=_options(config))
