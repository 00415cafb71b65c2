"""Ablations of ``ssf`` (SSF-PAN Table I): which half of "segmentation + scene flow" helps.

Each ablation is the ``ssf`` stage chain (:mod:`flowslam.frontends.ssf_stages`) with one
stage added, swapped or left out, run by :class:`flowslam.frontends.ssf.SsfFrontend`
(the window of past scans, compensated with the frontend's *own* pose estimates, never
GT). Table I marks each row by what it takes from the ground truth:

============================  =========  ======================================================
frontend                      marker     segmentation / flow used for the odometry
============================  =========  ======================================================
``ssf``                       ●          predicted / predicted (refined)
``sf``                        ●          none (every point registered) / predicted (network)
``gt-flow+ssf-seg``           ○          predicted (the full ``ssf`` chain) / **GT** ``gt_flow``
``gt-seg``                    ◐          **GT** ``~gt_dynamic`` / predicted (refined)
``gt``                        (GT)       **GT** ``~gt_dynamic`` / **GT** ``gt_flow``
``gt-flow``                   (GT flow)  none / **GT** ``gt_flow``
``ransac``, ``kiss-icp``      (none)     baselines: no scene flow
============================  =========  ======================================================

● = segmentation and scene flow both predicted; ○ = predicted segmentation with
ground-truth scene flow; ◐ = predicted scene flow with ground-truth segmentation (the
paper draws both ablations hollow; ``flowslam bench`` tells them apart with ◐, see
``flowslam.benchmark.suite.KINDS``). Importing this module imports neither torch nor
Open3D (the stages import them lazily).

- ``sf`` (scene-flow odometry without motion segmentation): ``network`` → ``no_segmentation``
  (the network's static mask is dropped) → ``flow_to_pose`` on every point with finite flow:
  the robust registration alone must reject the movers. No test-time refinement (it picks
  static points, i.e. it segments), no objects, whatever ``ssf.refine``/``ssf.objects`` say.
  Outputs: the network's flow, ``static_mask`` None, no instances.
- ``gt-seg`` (predicted flow, GT segmentation; reads ``Frame.gt_dynamic`` and, if
  present, ``Frame.gt_instance``): ``network`` → ``gt_segmentation`` (static = ``~gt_dynamic``)
  → ``pose_start`` → ``refine`` → ``flow_to_pose`` → ``static_flow``, as ``ssf`` with
  ``objects.enabled: false`` (the segmentation is already GT). The flow is the network's,
  refined; never GT flow. Instances: ``gt_instance`` on GT-dynamic points, -1 elsewhere.
- ``gt-flow+ssf-seg`` (GT flow, predicted segmentation; reads ``Frame.gt_flow``): the full
  ``ssf`` chain, objects included, gives the static mask and instances; then
  ``gt_flow_to_pose`` registers the GT flow of those predicted-static points and that is the
  odometry measurement (and so the pose that feeds the chain's window at the next scan).
  Outputs: the GT flow, the predicted static mask and instances.

The GT ablations refuse a frame pair whose scan k-1 lacks the GT they read with one
``InputError`` naming that scan's file (the CLI prints it as one line, exit code 2), at
every pair: a run never silently mixes GT and predictions.

Frames and units as in :mod:`flowslam.interfaces`: per-point outputs refer to scan k-1
(sensor frame k-1), flow in the Argoverse 2 convention (m, ``p + flow`` in sensor frame k),
``T_prev_curr`` maps scan k into frame k-1, covariance 6x6 [rad, m].
"""

from __future__ import annotations

import numpy as np

from flowslam import geometry
from flowslam.config import PipelineConfig
from flowslam.errors import InputError
from flowslam.frontends.ssf import SsfFrontend
from flowslam.frontends.ssf_stages import FlowToPoseStage, NetworkStage, PairState, Stage, build_stages

__all__ = ["make_sf_frontend", "make_gt_seg_frontend", "make_gt_flow_ssf_seg_frontend"]

_GT_FIELDS = {"gt_flow": "ground-truth flow", "gt_dynamic": "ground-truth dynamic labels"}


class RequireGroundTruthStage:
    """Stops the run with an ``InputError`` when scan k-1 lacks a GT field the ablation reads."""

    name = "gt_check"

    def __init__(self, frontend: str, field: str):
        self.frontend, self.field = frontend, field

    def run(self, state: PairState) -> None:
        if getattr(state.prev, self.field) is None:
            raise InputError(
                state.prev.where,
                f"has no {_GT_FIELDS[self.field]}; the {self.frontend} frontend needs a dataset with "
                "them (simulated sequences, Argoverse 2 with flow_labels)",
            )


class NoSegmentationStage:
    """``sf``: the network's static mask is dropped, every point goes to the registration."""

    name = "no_segmentation"

    def run(self, state: PairState) -> None:
        state.static = None


class GtSegmentationStage:
    """``gt-seg``: static = ``~gt_dynamic`` of scan k-1; instances = ``gt_instance`` of its
    dynamic points (-1 elsewhere; none without instance labels)."""

    name = "gt_segmentation"

    def run(self, state: PairState) -> None:
        prev = state.prev
        dynamic = np.asarray(prev.gt_dynamic, dtype=bool)
        state.static = ~dynamic
        state.instance = None if prev.gt_instance is None else np.where(dynamic, prev.gt_instance, -1)


class GtFlowToPoseStage(FlowToPoseStage):
    """``gt-flow+ssf-seg``: the measurement is ``FlowToPose`` on the GT flow of the points the
    chain so far calls static; the flow output becomes the GT flow."""

    name = "gt_flow_to_pose"

    def run(self, state: PairState) -> None:
        predicted = state.estimate
        state.flow = np.asarray(state.prev.gt_flow, dtype=np.float64)
        state.estimate = self.flow_to_pose.estimate(state.prev.points, state.flow, static_mask=state.static,
                                                    dt=state.dt)
        state.stats.update(
            ssf_fallback=bool(predicted.fallback),
            ssf_odometry_delta_m=geometry.translation_norm(geometry.inv(predicted.T_prev_curr)
                                                          @ state.estimate.T_prev_curr),
        )


def _ssf_chain(config: PipelineConfig, objects: bool) -> list[Stage]:
    options = config.ssf
    if not objects:
        options = options.model_copy(update={"objects": options.objects.model_copy(update={"enabled": False})})
    return build_stages(options, config.flow_odometry)


def make_sf_frontend(config: PipelineConfig) -> SsfFrontend:
    """``sf``: the network's flow of every point -> robust registration (module doc)."""
    stages = [NetworkStage(config.ssf), NoSegmentationStage(), FlowToPoseStage(config.flow_odometry)]
    return SsfFrontend(config.ssf, config.flow_odometry, stages=stages, name="sf")


def make_gt_seg_frontend(config: PipelineConfig) -> SsfFrontend:
    """``gt-seg``: predicted (refined) flow, GT segmentation (module doc)."""
    network, *rest = _ssf_chain(config, objects=False)  # the chain always starts with the network
    stages = [RequireGroundTruthStage("gt-seg", "gt_dynamic"), network, GtSegmentationStage(), *rest]
    return SsfFrontend(config.ssf, config.flow_odometry, stages=stages, name="gt-seg")


def make_gt_flow_ssf_seg_frontend(config: PipelineConfig) -> SsfFrontend:
    """``gt-flow+ssf-seg``: the ``ssf`` segmentation, the GT flow registered (module doc)."""
    stages = [RequireGroundTruthStage("gt-flow+ssf-seg", "gt_flow"), *_ssf_chain(config, objects=True),
              GtFlowToPoseStage(config.flow_odometry)]
    return SsfFrontend(config.ssf, config.flow_odometry, stages=stages, name="gt-flow+ssf-seg")
