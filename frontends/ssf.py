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
   With objects on, ``scan_index`` then builds what the objects stage asks of the two
   scans (scan k's surface index and range image, scan k-1's local ground).
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

Two threads (``ssf.lookahead``, on by default): the run loop reads one scan ahead and
hands it over (``upcoming``); as soon as scan k's pose is measured (after ``recovery``),
stages 1-3 of pair (k, k+1) (and ``scan_index``, unless the caller's thread claims it
first when it comes to wait for them) start in a background thread, while the objects stage of
pair (k-1, k), the backend, mapping and loop closing run in the caller's. Those stages
read only the scans and the frontend's own poses up to k, the same inputs as in one
thread, so the outputs are the same; ``process`` then takes their result
(``stats["ahead_wait_ms"]``: how long it waited for it). A caller that never
calls ``upcoming`` gets the one-thread behaviour.

``ssf.early_network`` (opt-in): the network places its input scans with scan k's pose from
the pose start (``T_world_{k-1}`` times the pose start's step) rather than the refined one,
so the network and pose start of pair (k, k+1) start in the background as soon as pair
(k-1, k)'s pose start is known, and the static refinement runs in the caller's thread
beside them. One thread gives the same outputs (the same network poses); a retry of the
recovery first ends and drops the pair running ahead (``MotionRecoveryStage.before_retry``),
which starts again once scan k's pose is measured.

Per-point outputs (flow, static mask, instance ids) refer to scan ``k-1``, as the
interface says; ``stats["stage_ms"]`` holds each stage's wall time, ``stats["recovery"]``
the motion-fault check (counted in run.json's ``fallbacks`` entry).
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from flowslam import geometry
from flowslam.config import FlowOdometryConfig, PipelineConfig, SsfConfig
from flowslam.frame import Frame
from flowslam.frontends.ssf_stages import (
    MotionRecoveryStage,
    NetworkStage,
    PairState,
    PoseStartStage,
    Stage,
    build_stages,
    network_guess,
    network_poses,
    restore_motion_models,
    snapshot_motion_models,
)
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
        measuring = [i for i, s in enumerate(self.stages) if getattr(s, "measures", False)]
        self._ahead_stages = self.stages[:measuring[0]] if measuring else []
        """The stages that may run ahead on the next pair (``Stage`` doc)."""
        self._measured_after = measuring[-1] if measuring else len(self.stages) - 1
        """Index of the stage after which scan k's pose is final."""
        starts = [i for i, s in enumerate(self._ahead_stages) if isinstance(s, PoseStartStage)]
        self._early = bool(self.options.early_network and starts)
        """``ssf.early_network``: the next pair's stages up to its pose start run ahead as soon
        as this pair's pose start is known (module doc)."""
        if self._early:
            self._ahead_stages = self._ahead_stages[:starts[0] + 1]
            for stage in self.stages:
                if isinstance(stage, MotionRecoveryStage):
                    stage.before_retry = self._drop_ahead
        self._start_pose = np.eye(4)  # scan k-1's T_world_sensor from the pose start (``ssf.early_network``)
        self._start_step = np.eye(4)  # the pose start's step T_prev_curr into scan k-1
        self._upcoming: Frame | None = None
        self._ahead: _StagesAhead | None = None
        self._executor = None

    def upcoming(self, frame: Frame) -> None:
        """The scan after the one the next :meth:`process` call gets, read ahead by the run
        loop: with ``ssf.lookahead`` the first stages of its pair run in a background thread
        as soon as that call has measured its pose (module doc). Optional for callers."""
        self._upcoming = frame if self.options.lookahead and self._ahead_stages else None

    def process(self, frame: Frame) -> FrontendOutput:
        if not self._frames:
            self._advance(frame, np.eye(4), np.eye(4))
            return FrontendOutput(index=frame.index, T_prev_curr=None)
        state = fresh = self._pair_state(frame)
        laps: dict[str, float] = {}
        first, waited = 0, {}
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead.serves(state):
            built = {}  # what the caller's thread builds for the objects stage while it would wait
            for stage in self._ahead_stages:
                ms = stage.claim(ahead.state) if hasattr(stage, "claim") else None
                if ms is not None:
                    built[stage.name] = ms
            start = time.perf_counter()
            state, laps = ahead.result()  # raises what those stages raised
            waited = {"ahead_wait_ms": 1e3 * (time.perf_counter() - start)}
            laps.update(built)
            first = len(self._ahead_stages)
            if self._early:  # run ahead on its network's poses; the caller's stages use the measured ones
                state.history_poses, state.T_world_guess = fresh.history_poses, fresh.T_world_guess
        elif ahead is not None:
            ahead.discard()  # another pair: as if it never ran
        for i in range(first, len(self.stages)):
            if self._early and i == len(self._ahead_stages):  # this pair's pose start is known
                self._start_early(frame, state)
            laps.update(_run_timed(self.stages[i:i + 1], state))
            if i == self._measured_after:  # the pose of scan k is final
                if self._early:
                    self._start_pose, self._start_step = self._started(state)
                self._advance(frame, state.T_world_measured, state.estimate.T_prev_curr)
        est = state.estimate
        dynamic = {} if state.static is None else {"dynamic_points": int((~state.static).sum())}  # None: unsegmented
        stats = dict(est.stats, **dynamic, **state.stats, **waited, stage_ms=laps)
        return FrontendOutput(
            index=frame.index, T_prev_curr=est.T_prev_curr, covariance=est.covariance,
            points=state.prev.points, flow=state.flow, static_mask=state.static,
            instance_ids=state.instance, stats=stats,
        )

    def _pair_state(self, frame: Frame) -> PairState:
        """The pair (last scan, ``frame``) with the window of past scans and own poses, and
        the constant-velocity guess of ``frame``'s pose; with ``ssf.early_network`` also the
        network's poses (the last scan's from its pose start)."""
        state = PairState(prev=self._frames[-1], frame=frame, history=list(self._frames),
                          history_poses=list(self._poses), T_world_guess=self._poses[-1] @ self._last_motion)
        if self._early:
            state.network_poses = self._early_poses(list(self._poses)[:-1], self._start_pose)
            state.network_guess = self._start_pose @ self._start_step
        return state

    def _early_poses(self, before: list[np.ndarray], start_pose: np.ndarray) -> list[np.ndarray]:
        """``ssf.early_network``: the network's poses of a window, the refined ``before`` (the
        scans before its newest) and the newest scan's ``start_pose``, the last T - 1 of them."""
        return (before + [start_pose])[-(self.num_frames - 1):]

    def _started(self, state: PairState) -> tuple[np.ndarray, np.ndarray]:
        """(scan k's ``T_world_sensor`` from ``state``'s pose start, that step as ``T_prev_curr``)."""
        step = geometry.inv(state.T_start)
        return state.history_poses[-1] @ step, step

    def _start_early(self, frame: Frame, state: PairState) -> None:
        """``ssf.early_network``: the stages up to the pose start of the upcoming pair (``frame``,
        next) start in the background, on the network's poses :meth:`_pair_state` will give that
        pair (scan k's from this pair's pose start); the caller's stages of this pair go on."""
        upcoming, self._upcoming = self._upcoming, None
        if upcoming is None or upcoming.index <= frame.index:
            return
        pose, step = self._started(state)
        frames = (list(self._frames) + [frame])[-(self.num_frames - 1):]
        poses, guess = self._early_poses(list(self._poses), pose), pose @ step
        # scan k's refined pose is not known yet: the caller's stages get it when they take this state
        ahead = PairState(prev=frame, frame=upcoming, history=frames, history_poses=poses, T_world_guess=guess,
                          network_poses=poses, network_guess=guess)
        self._submit(ahead)

    def _drop_ahead(self) -> None:
        """End and drop the stages running ahead (before a retry re-runs the same stage
        objects); the upcoming scan starts again once this pair's pose is measured."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None:
            ahead.discard()
            self._upcoming = ahead.state.frame

    def _advance(self, frame: Frame, T_world_frame: np.ndarray, T_prev_curr: np.ndarray) -> None:
        """``frame`` joins the window with its pose; the first stages of the upcoming pair start."""
        self._last_motion = T_prev_curr
        self._frames.append(frame)
        self._poses.append(T_world_frame)
        upcoming, self._upcoming = self._upcoming, None
        if upcoming is not None and upcoming.index > frame.index:
            state = self._pair_state(upcoming)
            state.scan_index_claim = threading.Lock()
            self._submit(state)

    def _submit(self, state: PairState) -> None:
        """Run the ahead stages on ``state`` in the background thread."""
        if self._executor is None:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ssf-ahead")
        saved = snapshot_motion_models(self._ahead_stages)
        self._ahead = _StagesAhead(state, self._executor.submit(_run_timed, self._ahead_stages, state), saved)


def _run_timed(stages: list[Stage], state: PairState) -> dict[str, float]:
    """Run ``stages`` on ``state`` in order; the wall time of each (ms)."""
    laps = {}
    for stage in stages:
        start = time.perf_counter()
        stage.run(state)
        laps[stage.name] = 1e3 * (time.perf_counter() - start)
    return laps


class _StagesAhead:
    """The first stages of a pair, run in the background (``SsfFrontend._advance``)."""

    def __init__(self, state: PairState, future, motion_models: list):
        self.state, self.future = state, future
        self.motion_models = motion_models
        """The stages' predictor states before they ran (``snapshot_motion_models``)."""

    def serves(self, state: PairState) -> bool:
        """Whether ``state`` has exactly these inputs: the same scan objects and poses."""
        mine, theirs = self.state, state
        frames = [*mine.history, mine.frame], [*theirs.history, theirs.frame]
        poses = ([*network_poses(mine), network_guess(mine)], [*network_poses(theirs), network_guess(theirs)])
        return (len(frames[0]) == len(frames[1]) and all(a is b for a, b in zip(*frames))
                and all(np.array_equal(a, b) for a, b in zip(*poses)))

    def result(self) -> tuple[PairState, dict[str, float]]:
        """The state those stages filled and their wall times (ms)."""
        return self.state, self.future.result()

    def discard(self) -> None:
        """Wait for the stages to end, drop what they found and put their predictors back."""
        self.future.exception()  # waits; an error of a pair that is not run is no error
        restore_motion_models(self.motion_models)


def make_frontend(config: PipelineConfig) -> SsfFrontend:
    return SsfFrontend(config.ssf, config.flow_odometry)
