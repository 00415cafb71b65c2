"""Frontend ``ssf`` (first version): learned scene flow -> static mask -> flow-to-pose.

Per scan ``k`` (k >= 1):

1. The last ``T`` scans (oldest first; at the start the oldest available scan is
   repeated) are moved into sensor frame ``k`` with the frontend's *own* estimates:
   its chained odometry for the older scans and a constant-velocity prediction for
   the newest step. No ground truth is read.
2. ``SceneFlowNet`` predicts the residual flow and a dynamic logit for a sample of the
   points of scan ``k-1``; the prior is added back and both are propagated to every
   point of scan ``k-1`` (``flowslam.sceneflow.propagate``): full Argoverse-2-convention
   flow (m, sensor frame k) and a static mask (dynamic probability < 0.5).
3. ``FlowToPose`` registers the static flow pairs (IRLS / RANSAC) into a first motion
   estimate (constant-velocity fallback when degenerate).
4. Test-time refinement (``refine``, on by default; ``flowslam.sceneflow.refine``): the
   static flow is refined against the geometry of scan ``k`` by flow-guided
   point-to-plane ICP, and ``FlowToPose`` turns the refined static flow into the
   odometry measurement ``T_prev_curr`` and its covariance. The static points' output
   flow is then the rigid flow of that measurement; dynamic points keep the network's
   flow. With ``refine.enabled: false`` step 3 gives the measurement (network flow only).
5. Objects (``objects``, on by default, needs step 4; ``flowslam.sceneflow.objects``):
   candidate moving points are clustered and each object is registered to scan ``k``
   (rigid ICP from the network's displacement); its points get that rigid flow and a
   dynamic label from its speed relative to the ego motion. Geometric movers (points that
   left the space scan ``k`` now sees through, ``flowslam.sceneflow.visibility``) are
   candidates too, with extra ICP starts along their axis. The moving points found for
   one pair are carried over to the next (``MoverPrior``, constant object velocity) as
   extra candidates with a predicted flow, so an object found once stays tracked.

Per-point outputs (flow, static mask) refer to scan ``k-1``, as the interface says.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from flowslam import geometry
from flowslam.datasets.frame import Frame
from flowslam.flow_odometry import FlowOdometryConfig, FlowToPose
from flowslam.interfaces import FrontendOutput
from flowslam.sceneflow.objects import MoverPrior, ObjectRefinementConfig, refine_objects
from flowslam.sceneflow.refine import FlowRefinementConfig, refine_static_flow
from flowslam.sceneflow.visibility import MotionEvidenceConfig, geometric_movers


class SsfConfig(BaseModel):
    """Options of the ``ssf`` frontend."""

    model_config = ConfigDict(extra="forbid")

    weights: Path | None = None
    """Weights file; None = the weights shipped in the package (hash-checked)."""
    max_points: int = 16384
    """Points sampled per scan for the network (flow is propagated to all points)."""
    dynamic_threshold: float = 0.3
    """A point is a dynamic candidate when sigmoid(logit) exceeds this (the objects step
    verifies candidates, so recall matters more than precision: 0.3 beat 0.5 on the
    held-out simulated sequences used for tuning)."""
    device: str = "cpu"
    num_threads: int | None = None
    refine: FlowRefinementConfig = FlowRefinementConfig()
    """Test-time refinement of the static flow against the next scan (module doc, step 4)."""
    objects: ObjectRefinementConfig = ObjectRefinementConfig()
    motion_evidence: MotionEvidenceConfig = MotionEvidenceConfig()
    """Geometric movers (off surface, seen through) added to the objects' candidates."""
    """Test-time rigid refinement of the moving objects' flow (module doc, step 5)."""


class _StageClock:
    """Wall time of consecutive stages (ms), for ``FrontendOutput.stats["stage_ms"]``."""

    def __init__(self):
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + 1e3 * (now - self._t)
        self._t = now


class SsfFrontend:
    name = "ssf"

    def __init__(self, options: SsfConfig | None = None, flow_odometry: FlowOdometryConfig | None = None):
        import torch

        from flowslam.sceneflow.weights import build_model, load_weights, shipped_weights

        self.options = options = options or SsfConfig()
        if options.num_threads:
            torch.set_num_threads(options.num_threads)
        path = options.weights or shipped_weights()
        payload = load_weights(path, require_hash=options.weights is None)
        self.device = torch.device(options.device)
        self.model = build_model(payload).to(self.device)
        if self.device.type == "cpu":
            from flowslam.sceneflow.model import tune_cpu_allocator

            self.model.fold_batchnorm()  # inference only: BatchNorm folded into the convolutions
            tune_cpu_allocator()
        self.num_frames = self.model.config.num_frames
        self.flow_to_pose = FlowToPose(flow_odometry)
        # step 3 when refining: only the ICP's start, so IRLS on 5000 pairs, no RANSAC rescue
        # and no degeneracy check (the refined registration gets the full treatment)
        start = (flow_odometry or FlowOdometryConfig()).model_copy(
            update={"ransac_below_inlier_ratio": 0.0, "max_points": 5000, "check_geometry": False}
        )
        self._network_pose = FlowToPose(start)
        self._frames: deque[Frame] = deque(maxlen=self.num_frames - 1)
        self._poses: deque[np.ndarray] = deque(maxlen=self.num_frames - 1)  # own T_world_sensor estimates
        self._last_motion = np.eye(4)
        self._movers = MoverPrior(self.options.objects.track_radius_m)

    def _priors(self, T_world_new: np.ndarray) -> tuple[list[Frame], list[np.ndarray]]:
        frames, poses = list(self._frames), list(self._poses)
        while len(frames) < self.num_frames - 1:  # start of a sequence: repeat the oldest scan
            frames.insert(0, frames[0])
            poses.insert(0, poses[0])
        T_new_world = geometry.inv(T_world_new)
        return frames, [T_new_world @ T for T in poses] + [np.eye(4)]

    def _predict(self, frame: Frame, T_world_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network flow (full, AV2 convention, frame of ``frame``) and dynamic probability of
        every point of the previous scan, with ``T_world_new`` the guess of the new pose."""
        import torch

        from flowslam.sceneflow.model import full_flow
        from flowslam.sceneflow.propagate import propagate
        from flowslam.sceneflow.samples import frames_to_sample

        frames, priors = self._priors(T_world_new)
        sample = frames_to_sample(frames + [frame], priors, self.options.max_points)
        prev = frames[-1]
        with torch.no_grad():
            out = self.model({"points": [[torch.from_numpy(p).to(self.device) for p in sample.points]]})
            values = propagate(
                torch.from_numpy(prev.points).to(self.device).float(),
                torch.from_numpy(sample.source_index).to(self.device),
                torch.cat([out["flow"].float(), out["dynamic_logit"].float()[:, None]], dim=1),
            ).cpu().numpy().astype(np.float64)
        compensated = geometry.transform_points(sample.T_new_src, prev.points)
        return full_flow(prev.points, compensated, values[:, :3]), 1.0 / (1.0 + np.exp(-values[:, 3]))

    def process(self, frame: Frame) -> FrontendOutput:
        from scipy.spatial import cKDTree

        if not self._frames:
            self._frames.append(frame)
            self._poses.append(np.eye(4))
            return FrontendOutput(index=frame.index, T_prev_curr=None)
        T_world_prev = self._poses[-1]
        prev = self._frames[-1]
        clock = _StageClock()
        flow, dynamic_prob = self._predict(frame, T_world_prev @ self._last_motion)  # constant velocity
        static = dynamic_prob < self.options.dynamic_threshold
        clock.lap("network")
        dt = frame.timestamp - prev.timestamp
        refine_stats: dict = {}
        if self.options.refine.enabled:
            first = self._network_pose.estimate(prev.points, flow, static_mask=static, dt=dt)
            clock.lap("network_pose")
            refined = refine_static_flow(prev.points, flow, static, frame.points, first.T_curr_prev,
                                         self.options.refine)
            refine_stats = dict(refined.stats, refine_accepted=refined.accepted)
            clock.lap("refine")
        if self.options.refine.enabled and refined.accepted:
            est = self.flow_to_pose.estimate(refined.points, refined.flow, dt=dt)
            clock.lap("flow_to_pose")
            if self.options.objects.enabled:
                dynamic = ~static
                tracked, tracked_flow = self._movers.predict(prev.points, est.T_curr_prev)
                flow = np.where(tracked[:, None], tracked_flow, flow)  # last pair's movers, moved on
                dynamic |= tracked
                movers = seen = None
                if self.options.motion_evidence.enabled:
                    movers, seen = geometric_movers(prev.points, frame.points, est.T_curr_prev,
                                                    self.options.motion_evidence)
                objects = refine_objects(prev.points, flow, dynamic, frame.points, est.T_curr_prev, dt,
                                         self.options.objects, cKDTree(refined.target_points), movers, seen)
                flow, static = objects.flow, ~objects.dynamic
                self._movers.update(prev.points, flow, objects.dynamic, est.T_curr_prev)
                refine_stats.update(objects.stats, tracked_candidates=int(tracked.sum()))
            else:
                flow = flow.copy()  # static points: the rigid flow of the measurement
                flow[static] = geometry.transform_points(est.T_curr_prev, prev.points[static]) - prev.points[static]
            clock.lap("objects" if self.options.objects.enabled else "static_flow")
        else:
            est = self.flow_to_pose.estimate(prev.points, flow, static_mask=static, dt=dt)
            clock.lap("flow_to_pose")
        self._last_motion = est.T_prev_curr
        self._frames.append(frame)
        self._poses.append(T_world_prev @ est.T_prev_curr)
        stats = dict(est.stats, dynamic_points=int((~static).sum()), **refine_stats, stage_ms=clock.laps)
        return FrontendOutput(
            index=frame.index, T_prev_curr=est.T_prev_curr, covariance=est.covariance,
            points=prev.points, flow=flow, static_mask=static, stats=stats,
        )


def make_frontend(config) -> SsfFrontend:
    return SsfFrontend(getattr(config, "ssf", None), getattr(config, "flow_odometry", None))
