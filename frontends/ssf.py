"""Frontend ``ssf``: learned scene flow, refined at test time, segmented, turned into odometry.

Per scan ``k`` (k >= 1) a chain of stages runs on the pair (k-1, k)
(``flowslam.frontends.ssf_stages``; options ``ssf.<stage>`` in the run config):

1. ``network``: the last ``T`` scans (oldest first; at the start the oldest available
   scan is repeated) are moved into sensor frame ``k`` with the frontend's *own*
   estimates: its chained odometry for the older scans and a constant-velocity
   prediction for the newest step. No ground truth is read. ``SceneFlowNet`` predicts
   the residual flow and a dynamic logit for a sample of the points of scan ``k-1``;
   the prior is added back and both are propagated to every point of scan ``k-1``:
   full Argoverse-2-convention flow (m, sensor frame k) and a static mask (dynamic
   probability below ``network.dynamic_threshold``).
2. ``pose_start`` (with ``refine``): ``FlowToPose`` on the network's static flow, with
   the cheap options of ``ssf.pose_start``, gives the ICP's start.
3. ``refine`` (``ssf.refine.enabled``, on by default): the static flow is refined against
   the geometry of scan ``k`` by flow-guided point-to-plane ICP; static points are
   snapped onto scan k's surface.
4. ``flow_to_pose``: ``FlowToPose`` (``flow_odometry:``) registers the snapped static
   pairs (or, without an accepted refinement, the network's static flow) into the
   odometry measurement ``T_prev_curr`` and its covariance.
5. ``recovery`` (with ``refine``; ``ssf.recovery``): the step is checked for a motion
   fault from its own evidence (a fallback, a rejected refinement, a drop in the
   refinement's fitness or a jump in the dynamic share against the last good steps, a
   large disagreement with the constant-velocity prior; no ground truth). A faulty step
   is re-initialised globally (FPFH + RANSAC of scan k onto scan k-1), stages 1-4 run
   again from that start, and the solution that explains more of scan k is kept
   (``docs/motion_recovery.md``). Only the check runs on a good step.
6. ``objects`` (``ssf.objects.enabled``, on by default; needs an accepted refinement):
   candidate moving points (network dynamic, the last pair's movers carried on at
   constant velocity, geometric movers seen through in scan k's range image) are
   clustered and each object is registered to scan ``k`` by rigid ICP; its points get
   that rigid flow, a dynamic label from its speed relative to the ego motion and an
   instance id. With objects off, the static points get the rigid flow of the
   measurement instead (``static_flow``).

Per-point outputs (flow, static mask, instance ids) refer to scan ``k-1``, as the
interface says; ``stats["stage_ms"]`` holds each stage's wall time, ``stats["recovery"]``
the motion-fault check (counted in run.json's ``fallbacks`` entry).
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from flowslam.config import FlowOdometryConfig, PipelineConfig, SsfConfig
from flowslam.frame import Frame
from flowslam.frontends.ssf_stages import MotionRecoveryStage, NetworkStage, PairState, Stage, build_stages
from flowslam.interfaces import FrontendOutput


class SsfFrontend:
    """The stage chain of the module doc, with the window of past scans and own poses."""

    name = "ssf"
    config_sections = ("ssf", "flow_odometry")
    """The config sections it reads (an option of another section given on the command line is an error)."""

    def __init__(self, options: SsfConfig | None = None, flow_odometry: FlowOdometryConfig | None = None,
                 stages: list[Stage] | None = None, name: str | None = None):
        """``stages``: another chain (it must hold a ``NetworkStage``), e.g. the ablations of
        ``flowslam.frontends.ssf_ablations``; default ``build_stages(options, flow_odometry)``."""
        self.options = options or SsfConfig()
        if stages is None:
            stages = build_stages(self.options, flow_odometry or FlowOdometryConfig())
        self.stages = stages
        for i, stage in enumerate(stages):  # a retry re-runs this chain's stages before the recovery
            if isinstance(stage, MotionRecoveryStage):
                stage.attach(stages[:i])
        self.name = name or self.name
        network = next(s for s in self.stages if isinstance(s, NetworkStage))
        self.num_frames = network.num_frames
        self.info = {"weights": network.weights_info}
        """What ``run.json`` records about this frontend (``frontend_info``)."""
        self._frames: deque[Frame] = deque(maxlen=self.num_frames - 1)
        self._poses: deque[np.ndarray] = deque(maxlen=self.num_frames - 1)  # own T_world_sensor estimates
        self._last_motion = np.eye(4)

    def process(self, frame: Frame) -> FrontendOutput:
        if not self._frames:
            self._frames.append(frame)
            self._poses.append(np.eye(4))
            return FrontendOutput(index=frame.index, T_prev_curr=None)
        T_world_prev = self._poses[-1]
        state = PairState(
            prev=self._frames[-1], frame=frame, history=list(self._frames), history_poses=list(self._poses),
            T_world_guess=T_world_prev @ self._last_motion,  # constant velocity
        )
        laps: dict[str, float] = {}
        for stage in self.stages:
            start = time.perf_counter()
            stage.run(state)
            laps[stage.name] = 1e3 * (time.perf_counter() - start)
        est = state.estimate
        self._last_motion = est.T_prev_curr
        self._frames.append(frame)
        self._poses.append(T_world_prev @ est.T_prev_curr)
        dynamic = {} if state.static is None else {"dynamic_points": int((~state.static).sum())}  # None: unsegmented
        stats = dict(est.stats, **dynamic, **state.stats, stage_ms=laps)
        return FrontendOutput(
            index=frame.index, T_prev_curr=est.T_prev_curr, covariance=est.covariance,
            points=state.prev.points, flow=state.flow, static_mask=state.static,
            instance_ids=state.instance, stats=stats,
        )


def make_frontend(config: PipelineConfig) -> SsfFrontend:
    return SsfFrontend(config.ssf, config.flow_odometry)
