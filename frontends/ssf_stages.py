"""The stages of the ``ssf`` frontend, one class each, run in order on one scan pair.

A stage reads and fills a :class:`PairState` (the pair (k-1, k) and what earlier stages
found) and has its own options section (``flowslam.config.ssf``) and its own entry in
``FrontendOutput.stats["stage_ms"]``:

================  ====================================================================
``network``       learned flow + dynamic probability of every point of scan k-1
``pose_start``    ``FlowToPose`` on the network's static flow -> ``T_start`` (ICP start)
``refine``        static refinement against scan k -> snapped static pairs
``scan_index``    scan k's surface index and range image, scan k-1's local ground
``flow_to_pose``  the odometry measurement ``T_prev_curr`` + covariance
``recovery``      motion-fault check; a faulty step re-initialised globally and re-run
``objects``       candidates -> objects -> per-point flow, dynamic label, instance
``static_flow``   (objects off) static points get the rigid flow of the measurement
================  ====================================================================

Frames: ``prev`` = scan k-1 (its sensor frame), ``frame`` = scan k; ``flow`` (N,3) over
the points of scan k-1, Argoverse 2 convention (``p + flow`` in sensor frame k, m);
``T_*_prev`` poses are ``T_world_sensor`` estimates of the frontend itself (never GT).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from flowslam import geometry
from flowslam.config import FlowOdometryConfig, SsfConfig
from flowslam.errors import InputError
from flowslam.frame import Frame
from flowslam.flow_odometry import FlowPoseEstimate, FlowToPose
from flowslam.sceneflow.refinement.static import RefinedFlow


@dataclass
class PairState:
    """What the stages know about the scan pair (k-1, k) (frames: module doc)."""

    prev: Frame
    """Scan k-1: the points every per-point array refers to."""
    frame: Frame
    """Scan k."""
    history: list[Frame]
    """The network's older input scans, oldest first, ending with ``prev``."""
    history_poses: list[np.ndarray]
    """The frontend's own ``T_world_sensor`` estimates of ``history``."""
    T_world_guess: np.ndarray
    """Constant-velocity guess of scan k's ``T_world_sensor`` (the network's ego prior)."""
    network_poses: list[np.ndarray] | None = None
    """With ``ssf.early_network``: the ``T_world_sensor`` the network places ``history`` with
    (scan k-1's from the pose start of pair (k-2, k-1)); None: ``history_poses``."""
    network_guess: np.ndarray | None = None
    """With ``ssf.early_network``: the network's guess of scan k's ``T_world_sensor``; None:
    ``T_world_guess``."""
    flow: np.ndarray | None = None
    """(N,3) flow of scan k-1's points (m, AV2 convention)."""
    dynamic_prob: np.ndarray | None = None
    """(N,) the network's dynamic probability."""
    static: np.ndarray | None = None
    """(N,) bool: static points (network threshold, then the objects stage's labels)."""
    instance: np.ndarray | None = None
    """(N,) int: moving-object instance of each point in this pair (-1: none)."""
    T_start: np.ndarray | None = None
    """``T_{k,k-1}`` from the network's static flow (start of the static refinement)."""
    refined: RefinedFlow | None = None
    """Snapped static pairs, when the refinement ran."""
    estimate: FlowPoseEstimate | None = None
    """The odometry measurement of the pair."""
    scan_index: ScanIndex | None = None
    """Scan k's surface index and range image and scan k-1's local ground, for the objects
    stage (``scan_index``)."""
    scan_index_claim: threading.Lock | None = None
    """Run ahead in the background (``ssf.lookahead``): whichever thread acquires it first
    builds ``scan_index`` (:class:`ScanIndexStage`); None: the caller runs every stage."""
    stats: dict = field(default_factory=dict)

    @property
    def dt(self) -> float:
        """Time between the scans (s)."""
        return self.frame.timestamp - self.prev.timestamp

    @property
    def refinement_accepted(self) -> bool:
        return self.refined is not None and self.refined.accepted

    @property
    def T_world_measured(self) -> np.ndarray:
        """Scan k's own ``T_world_sensor``: the window's last pose and the measured step
        (needs ``estimate``)."""
        return self.history_poses[-1] @ self.estimate.T_prev_curr

    @property
    def T_prior(self) -> np.ndarray:
        """The constant-velocity prior as ``T_prev_curr`` (scan k into frame k-1)."""
        return geometry.inv(self.history_poses[-1]) @ self.T_world_guess

    def retry(self, T_prev_curr: np.ndarray) -> PairState:
        """The same pair with nothing found yet and ``T_prev_curr`` as the prior."""
        return PairState(self.prev, self.frame, self.history, self.history_poses,
                         T_world_guess=self.history_poses[-1] @ T_prev_curr)

    def adopt(self, other: PairState) -> None:
        """Take every finding of ``other`` (a retry of this pair), its stats included."""
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(other, f.name))


def network_poses(state: PairState) -> list[np.ndarray]:
    """The ``T_world_sensor`` the network places ``state.history`` with."""
    return state.history_poses if state.network_poses is None else state.network_poses


def network_guess(state: PairState) -> np.ndarray:
    """The network's guess of scan k's ``T_world_sensor``."""
    return state.T_world_guess if state.network_guess is None else state.network_guess


class Stage(Protocol):
    name: str
    # Optional: ``measures = True`` on a stage that sets or changes ``state.estimate`` (the
    # pose of scan k). The stages before the first such stage see only the pair, its window
    # and the poses before it; those after the last one only refine per-point outputs. So
    # the first ones of the next pair may run while the last ones of this pair run
    # (``SsfFrontend``, ``ssf.lookahead``).

    def run(self, state: PairState) -> None:
        """Read and fill ``state``."""
        ...


class NetworkStage:
    """The learned network on the last T scans, compensated with the frontend's own poses
    (module doc of ``flowslam.frontends.ssf``); flow and probability for every point of
    scan k-1 (propagated from the sample)."""

    name = "network"

    def __init__(self, config: SsfConfig):
        from flowslam.threads import set_cache_defaults

        set_cache_defaults()  # before torch's first oneDNN kernel (flowslam.threads)
        import torch

        from flowslam.sceneflow.network.device import inference_device
        from flowslam.sceneflow.network.model import default_cpu_threads
        from flowslam.sceneflow.network.weights import build_model, load_weights, shipped_weights

        self.options = c = config.network
        self.device = inference_device(c.device)
        self._trim_every = 0  # heap trims: only after tuning the CPU allocator (below)
        threads = c.num_threads or (default_cpu_threads(config.lookahead) if self.device.type == "cpu" else None)
        if threads:
            torch.set_num_threads(threads)
        path = c.weights or shipped_weights()
        payload = load_weights(path, require_hash=c.weights is None)
        self.weights_info = {"path": str(path), "sha256": payload["sha256"]}
        """Which weights run (recorded in ``run.json``)."""
        self.model = build_model(payload).to(self.device)
        try:
            self.model.crop_grid(c.grid_half_extent_m)
        except ValueError as err:
            raise InputError("ssf.network.grid_half_extent_m", str(err)) from None
        if self.device.type == "cpu":
            from flowslam.sceneflow.network.model import tune_cpu_allocator

            self.model.fold_batchnorm()  # inference only: BatchNorm folded into the convolutions
            self._trim_every = c.trim_heap_every if tune_cpu_allocator() else 0
        self.num_frames = self.model.config.num_frames
        self._runs = 0

    def run(self, state: PairState) -> None:
        from flowslam.sceneflow.network.model import full_flow
        from flowslam.sceneflow.network.samples import transform_points_torch

        sample = self._sample(state)
        values = self._predict(sample, state.prev.points)
        prev = state.prev.points
        compensated = transform_points_torch(sample.T_new_src, prev)  # scan k-1 moved by the prior
        state.flow = full_flow(prev, compensated, values[:, :3])
        state.dynamic_prob = 1.0 / (1.0 + np.exp(-values[:, 3]))
        state.static = state.dynamic_prob < self.options.dynamic_threshold
        self._runs += 1
        if self._trim_every and self._runs % self._trim_every == 0:
            from flowslam.sceneflow.network.model import release_free_heap

            release_free_heap()

    def _sample(self, state: PairState):
        """The network input: the last T scans (the oldest repeated at the start of a
        sequence), sub-sampled, moved into scan k's sensor frame with the frontend's poses
        and the constant-velocity guess of scan k."""
        from flowslam.sceneflow.network.samples import frames_to_sample

        frames, poses = list(state.history), list(network_poses(state))
        while len(frames) < self.num_frames - 1:  # start of a sequence: repeat the oldest scan
            frames.insert(0, frames[0])
            poses.insert(0, poses[0])
        T_new_world = geometry.inv(network_guess(state))
        priors = [T_new_world @ T for T in poses] + [np.eye(4)]
        return frames_to_sample(frames + [state.frame], priors, self.options.max_points)

    def _predict(self, sample, points: np.ndarray) -> np.ndarray:
        """(N,4) float64 for all N ``points`` of scan k-1: residual flow (m, sensor frame
        k) and dynamic logit, predicted on the sample and propagated to every point."""
        import torch

        from flowslam.sceneflow.network.propagate import propagate

        bf16 = self.options.cuda_bf16 and self.device.type == "cuda"
        with torch.inference_mode(), torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
            out = self.model({"points": [[torch.from_numpy(p).to(self.device) for p in sample.points]]})
            values = torch.cat([out["flow"].float(), out["dynamic_logit"].float()[:, None]], dim=1)
            values = propagate(torch.from_numpy(points).to(self.device).float(),
                               torch.from_numpy(sample.source_index).to(self.device), values)
        return values.cpu().numpy().astype(np.float64)


class PoseStartStage:
    """``FlowToPose`` on the network's static flow with the cheap ``pose_start`` options."""

    name = "pose_start"

    def __init__(self, config: SsfConfig, flow_odometry: FlowOdometryConfig):
        self.flow_to_pose = FlowToPose(flow_odometry.model_copy(update=config.pose_start.model_dump()))

    def run(self, state: PairState) -> None:
        est = self.flow_to_pose.estimate(state.prev.points, state.flow, static_mask=state.static, dt=state.dt)
        state.T_start = est.T_curr_prev


class StaticRefinementStage:
    """Flow-guided point-to-plane ICP of the static points onto scan k, snapped pairs."""

    name = "refine"

    def __init__(self, config: SsfConfig):
        self.options = config.refine

    def run(self, state: PairState) -> None:
        from flowslam.sceneflow.refinement.static import refine_static_flow

        state.refined = refine_static_flow(state.prev.points, state.flow, state.static, state.frame.points,
                                           state.T_start, self.options)
        state.stats.update(state.refined.stats, refine_accepted=state.refined.accepted)


class FlowToPoseStage:
    """The odometry measurement: ``FlowToPose`` on the refined static pairs when the
    refinement was accepted, else on the network's static flow."""

    name = "flow_to_pose"
    measures = True

    def __init__(self, flow_odometry: FlowOdometryConfig):
        self.flow_to_pose = FlowToPose(flow_odometry)
        self._before: dict | None = None

    def run(self, state: PairState) -> None:
        self._before = self.flow_to_pose.predictor.snapshot()
        self._estimate(state)

    def rerun(self, state: PairState) -> None:
        """Measure the pair again (a retry): the motion model as it was before :meth:`run`."""
        self.flow_to_pose.predictor.restore(self._before)
        self._estimate(state)

    def _estimate(self, state: PairState) -> None:
        if state.refinement_accepted:
            state.estimate = self.flow_to_pose.estimate(state.refined.points, state.refined.flow, dt=state.dt,
                                                        geometry_points=state.refined.scene_points)
        else:
            state.estimate = self.flow_to_pose.estimate(state.prev.points, state.flow, static_mask=state.static,
                                                        dt=state.dt)


class MotionRecoveryStage:
    """Motion faults (``ssf.recovery``, :mod:`flowslam.registration.recovery`): every step is
    checked from its own evidence (free: numbers the stages computed anyway); a faulty step
    gets a global start (FPFH + RANSAC of scan k onto scan k-1), the ``redo`` stages and
    ``flow_to_pose`` run again from it (the network sees the new prior too), and the
    solution that explains more of scan k is kept (``AlignmentEvidence``), with the motion
    models' state of that solution. ``stats["recovery"]``: ``faults`` (cues, empty when
    good), ``outcome`` (None, ``recovered``, ``kept``, ``confirmed``, ``no_start``, ``off``),
    evidence before/after, the global start's stats and how far it lies from the step's
    solution; ``summarize_fallbacks`` counts them. A first step (cue ``first_step`` alone)
    whose global start agrees with its solution is ``confirmed`` without the retry."""

    name = "recovery"
    measures = True

    def __init__(self, config: SsfConfig, flow_to_pose: FlowToPoseStage):
        from flowslam.config import RansacConfig
        from flowslam.registration.global_registration import FpfhRansac
        from flowslam.registration.recovery import MotionFaultDetector

        self.options = config.recovery
        self.detector = MotionFaultDetector(self.options)
        self.redo: list[Stage] = []
        """The stages a retry runs before ``flow_to_pose`` (:meth:`attach`)."""
        self.flow_to_pose = flow_to_pose
        self.registration = FpfhRansac(RansacConfig(**self.options.global_start.model_dump()))
        self._features: dict[int, object] = {}  # scan index -> ScanFeatures (the last two)
        self.before_retry: Callable[[], None] | None = None
        """Called before a retry runs the ``redo`` stages (``ssf.early_network``: the frontend
        ends and drops the next pair's stages running ahead on the same stage objects)."""

    def attach(self, chain_before: list[Stage]) -> None:
        """The chain's stages before this one: a retry runs them again (all but
        ``flow_to_pose``, which is re-run last from the motion model's state before the step)."""
        self.redo = [s for s in chain_before if s is not self.flow_to_pose]

    def run(self, state: PairState) -> None:
        evidence = self._evidence(state)
        record: dict = {"faults": self.detector.check(evidence), "outcome": None}
        if not record["faults"]:
            self.detector.remember(evidence)
        elif not self.options.enabled:
            record["outcome"] = "off"
        else:
            record.update(self._recover(state, record["faults"]))
            if record["outcome"] in ("recovered", "kept", "confirmed"):  # kept, confirmed: the start agreed
                self.detector.remember(self._evidence(state))
        state.stats["recovery"] = record

    @staticmethod
    def _evidence(state: PairState):
        from flowslam.registration.recovery import StepEvidence, prior_disagreement

        rot, trans = prior_disagreement(state.T_prior, state.estimate.T_prev_curr)
        refined = state.refined
        return StepEvidence(
            fallback=state.estimate.fallback,
            refine_accepted=None if refined is None else refined.accepted,
            refine_fitness=None if refined is None else refined.stats.get("refine_fitness"),
            dynamic_share=None if state.static is None else float(np.mean(~state.static)),
            prior_rotation_rad=rot, prior_translation_m=trans)

    def _recover(self, state: PairState, faults: list[str]) -> dict:
        """Global start, then (unless it confirms a first step: :meth:`_confirms`) the retry
        from it; the outcome and its record (module doc of :mod:`flowslam.registration.recovery`)."""
        from flowslam.registration.recovery import AlignmentEvidence, global_start, prior_disagreement

        c = self.options
        T_start, start_stats = global_start(self._scan_features(state.frame), self._scan_features(state.prev),
                                            self.registration, c.global_start.min_fitness)
        if T_start is None:
            return {"outcome": "no_start", "global_start": start_stats}
        rot, trans = prior_disagreement(T_start, state.estimate.T_prev_curr)
        apart = {"start_apart_m": trans, "start_apart_deg": float(np.rad2deg(rot))}
        if self._confirms(faults, trans, rot):
            return {"outcome": "confirmed", "global_start": start_stats, **apart}
        evidence = AlignmentEvidence(state.frame.points, state.prev.points, c.evidence_voxel_m,
                                     c.evidence_distance_m, c.evidence_max_range_m)
        if self.before_retry is not None:
            self.before_retry()  # the stages of the next pair run ahead on these stages: end them first
        first_state = self._motion_models()
        trial = state.retry(T_start)
        for stage in self.redo:
            stage.run(trial)
        self.flow_to_pose.rerun(trial)
        before, after = evidence(state.estimate.T_prev_curr), evidence(trial.estimate.T_prev_curr)
        record = {"evidence_before": before, "evidence_after": after, "global_start": start_stats, **apart}
        if self._better(after, before, trial.estimate.fallback, state.estimate.fallback):
            state.adopt(trial)
            return dict(record, outcome="recovered")
        restore_motion_models(first_state)
        return dict(record, outcome="kept")

    def _confirms(self, faults: list[str], apart_m: float, apart_rad: float) -> bool:
        """Whether the global start confirms the step's own solution (it lies ``apart_m`` /
        ``apart_rad`` from it): the step's only cue is ``first_step`` (a check, not a sign of a
        fault) and the start is within ``confirm_translation_m`` and ``confirm_rotation_deg``.
        The retry would start where the solution already is, so it is not run."""
        c = self.options
        return (faults == ["first_step"] and apart_m < c.confirm_translation_m
                and np.rad2deg(apart_rad) < c.confirm_rotation_deg)

    def _better(self, after: float, before: float, after_fell_back: bool, before_fell_back: bool) -> bool:
        """The retry wins with more evidence by ``min_gain``, or, as a measurement against a
        prediction, with evidence not lower by ``min_gain``."""
        gain = self.options.min_gain
        if before_fell_back and not after_fell_back:
            return after >= before - gain
        return after > before + gain

    def _scan_features(self, frame: Frame):
        if frame.index not in self._features:
            self._features = {k: v for k, v in self._features.items() if k >= frame.index - 1}
            self._features[frame.index] = self.registration.features(frame.points, float(frame.timestamp))
        return self._features[frame.index]

    def _motion_models(self) -> list:
        """The constant-velocity predictors of the redo stages and ``flow_to_pose``, with their state."""
        return snapshot_motion_models([*self.redo, self.flow_to_pose])


def snapshot_motion_models(stages: list[Stage]) -> list:
    """(predictor, state) of every stage's ``FlowToPose`` constant-velocity predictor: what a
    stage carries from pair to pair, to put back with :func:`restore_motion_models`."""
    models = [s.flow_to_pose.predictor for s in stages if hasattr(s, "flow_to_pose")]
    return [(m, m.snapshot()) for m in models]


def restore_motion_models(saved: list) -> None:
    for model, snapshot in saved:
        model.restore(snapshot)


@dataclass
class ScanIndex:
    """What the objects stage asks of the pair's scans, built from the scans alone:
    ``surface``, the :class:`~flowslam.sceneflow.refinement.clusters.ScanSurface` of scan k
    (its cube index and BEV buckets built); ``image``, scan k's
    :class:`~flowslam.sceneflow.refinement.visibility.RangeImage` (None when neither the
    geometric movers nor the hidden-object test use one); ``ground``, the
    :class:`~flowslam.sceneflow.refinement.clusters.LocalGround` of scan k-1."""

    surface: object
    image: object
    ground: object

    @classmethod
    def build(cls, state: PairState, config: SsfConfig) -> ScanIndex:
        from flowslam.sceneflow.refinement.clusters import LocalGround, ScanSurface
        from flowslam.sceneflow.refinement.objects import object_target_range
        from flowslam.sceneflow.refinement.visibility import RangeImage

        c = config.objects
        evidence = c.motion_evidence
        # one index of scan k for both users: the movers' test reaches max_range_m + off_surface_m
        # (+ the ego motion), the objects' boxes object_target_range
        surface = ScanSurface(state.frame.points, max(object_target_range(c), evidence.max_range_m + 5.0))
        surface.prepare()
        # free space in scan k, for the movers' test and the (opt-in) hidden-object test
        image = RangeImage(state.frame.points, evidence) if evidence.enabled or c.hidden_test else None
        return cls(surface, image, LocalGround(state.prev.points, evidence.ground_cell_m))


class ScanIndexStage:
    """The objects stage's :class:`ScanIndex` of the pair (skipped when the static
    refinement was rejected: no objects stage then). It reads only the two scans, so with
    ``ssf.lookahead`` either thread may build it: the background thread after the static
    refinement, or the caller's thread (:meth:`claim`) when it comes to wait for the
    background before that; whichever gets there first (``PairState.scan_index_claim``).
    So it fills the thread that has time to spare: on real KITTI scans the caller's
    thread (objects, backend, map) sets the rate and the background one builds the index;
    on the simulated demo the network and refinement set it and the caller builds it while
    they run. The index is the same wherever it is built. The caller's thread claims it
    before the refinement's verdict is known, so on a pair whose refinement is rejected
    it may build an index that no objects stage uses."""

    name = "scan_index"

    def __init__(self, config: SsfConfig):
        self.config = config

    def run(self, state: PairState) -> None:
        if state.refinement_accepted and _claimed(state):
            state.scan_index = ScanIndex.build(state, self.config)

    def claim(self, state: PairState) -> float | None:
        """The caller's turn, before it waits for the stages run ahead on ``state``: build the
        index unless the background thread has claimed it; the ms it took, or None."""
        if state.scan_index_claim is None or not _claimed(state):
            return None
        start = time.perf_counter()
        state.scan_index = ScanIndex.build(state, self.config)
        return 1e3 * (time.perf_counter() - start)


def _claimed(state: PairState) -> bool:
    """Whether this thread may build ``state``'s scan index (the first to ask)."""
    return state.scan_index_claim is None or state.scan_index_claim.acquire(blocking=False)


class ObjectsStage:
    """Moving objects against scan k: candidates (network dynamic, tracked movers, geometric
    movers, slow movers against an older scan and, beyond ``long_baseline_from_m``, against
    a much older one) -> per-object ICP -> flow,
    dynamic labels and instances. Needs an accepted
    static refinement (the ego motion it verifies objects against); keeps the network's
    output otherwise.

    Scan k's surface index (cube index, normals, boxes) and scan k-1's local ground are
    built once per pair and shared by the sub-steps."""

    name = "objects"

    def __init__(self, config: SsfConfig):
        from flowslam.sceneflow.refinement.tracking import MoverPrior

        self.config = config
        self.options = config.objects
        c = self.options
        self.movers = MoverPrior(c.track_radius_m, radius_per_m=c.track_radius_per_m, max_radius_m=c.track_radius_max_m,
                                 grow_max_extent_m=c.track_grow_max_extent_m, max_quiet_pairs=c.track_max_quiet_pairs,
                                 quiet_min_extent_m=c.track_quiet_min_extent_m)
        self._images: dict[int, tuple] = {}
        """(range image, own ``T_world_sensor``) of the last scans by frame index: the older
        scans' free space for :func:`~flowslam.sceneflow.refinement.visibility.slow_movers`
        (each scan's image is built once, when it is scan k)."""
        self._surface: tuple = (None, None)
        """(frame index, :class:`ScanSurface`) of the last scan k: scan k-1 of the next pair,
        whose arrivals ask it."""
        self._surfaces: dict[int, tuple] = {}
        """(:class:`ScanSurface` for nearest-point queries, own ``T_world_sensor``) of the last
        scans by frame index, kept from when each was scan k, for ``occupied_release_share``."""

    def run(self, state: PairState) -> None:
        from flowslam.sceneflow.refinement.objects import (
            SEEN_EVIDENCE_SHARE,
            hold_tracks,
            refine_objects,
            release_tracks,
            scan_interval,
        )
        from flowslam.sceneflow.refinement.tracking import object_evidence
        from flowslam.sceneflow.refinement.visibility import geometric_movers

        if not state.refinement_accepted:
            return
        c, prev, T_ego = self.options, state.prev.points, state.estimate.T_curr_prev
        evidence = c.motion_evidence
        index = state.scan_index or ScanIndex.build(state, self.config)  # built ahead (scan_index) or here
        surface, image, ground = index.surface, index.image, index.ground
        tracked, tracked_flow = self.movers.predict(prev, T_ego)
        flow = np.where(tracked[:, None], tracked_flow, state.flow)  # last pair's movers, moved on
        dynamic = ~state.static | tracked
        movers = seen = None
        if evidence.enabled:
            self._keep_image(state, image)
        # the scan baseline_scans before scan k-1: for the slow movers and the held tracks
        older = self._older_view(state) if evidence.enabled or c.hold_tracks else None
        if evidence.enabled:
            movers, seen = geometric_movers(prev, state.frame.points, T_ego, evidence, surface, ground, image,
                                            *(self._prev_scan(state) if evidence.arrivals else ()))
            movers |= self._slow_movers(state, ground, older)
            movers |= self._hidden_slow_movers(state, ground, older)
            long = self._long_slow_movers(state, ground)
            if long is not None:
                movers |= long
            if evidence.arrivals:
                self._surface = (state.frame.index, surface)
        above = ground.above(evidence.ground_clearance_m)  # road clusters and growth
        # tracked parts (tracked_parts_min_points): what the track carried and the network flags too
        objects = refine_objects(prev, flow, dynamic, state.frame.points, T_ego, state.dt, c,
                                 state.refined.target_points, movers, seen, surface, above, image,
                                 tracked & ~state.static, self._slide_view(state, older))
        held = hold_tracks(prev, objects, tracked, tracked_flow, T_ego, state.dt, surface, older, c)
        shown = released = None
        if c.track_max_quiet_pairs > 0 or c.release_seen_share > 0:  # the objects' own evidence, besides the track
            flags = ~state.static if movers is None else ~state.static | movers | seen
            shown = object_evidence(flags, objects.instance, c.min_seen_through, SEEN_EVIDENCE_SHARE)
            asked, geometric = tracked, shown
            if c.release_any_prior and movers is not None:  # the network's labels are a prior too
                asked, geometric = None, object_evidence(movers | seen, objects.instance, c.min_seen_through,
                                                         SEEN_EVIDENCE_SHARE)
            span_s = self._scans_back(state, evidence.baseline_scans) * scan_interval(state.dt)
            released = release_tracks(prev, objects, asked, geometric, T_ego, older, span_s, c)
        occupied = self._release_occupied(state, objects, surface, above)
        # instances: accepted objects and the unregistered movers' (the rest: -1)
        kept = np.array([o["accepted"] or o.get("unregistered", False) for o in objects.objects] + [False])
        state.flow, state.static = objects.flow, ~objects.dynamic
        state.instance = np.where(kept[objects.instance], objects.instance, -1)
        self.movers.update(prev, objects.flow, objects.dynamic, T_ego, ground, state.instance, shown)
        state.stats.update(objects.stats, tracked_candidates=int(tracked.sum()), tracked_held=held)
        if released is not None:
            state.stats["tracked_released"] = released
        if occupied is not None:
            state.stats["occupied_released"] = occupied

    def _release_occupied(self, state: PairState, objects, surface, above) -> int | None:
        """:func:`~flowslam.sceneflow.refinement.occupancy.release_occupied` of the pair's
        ``objects`` against the kept surfaces of the scans ``occupied_from_scans`` to
        ``occupied_to_scans`` before scan k-1 (placed with the frontend's own poses), after
        keeping scan k's ``surface``; None when the option is off."""
        from flowslam.sceneflow.refinement.objects import scan_interval
        from flowslam.sceneflow.refinement.occupancy import OlderSurface, release_occupied

        c = self.options
        if c.occupied_release_share <= 0:
            return None
        k1 = state.prev.index
        self._surfaces = _keep_scan(self._surfaces, state, surface.nearest_only(), k1 - c.occupied_to_scans)
        T_world_prev = state.history_poses[-1]
        olders = [OlderSurface(old, geometry.inv(T_world_old) @ T_world_prev, back)
                  for back in range(c.occupied_from_scans, c.occupied_to_scans + 1)
                  for old, T_world_old in [self._surfaces.get(k1 - back, (None, None))] if old is not None]
        return release_occupied(state.prev.points, objects, above, state.estimate.T_curr_prev,
                                scan_interval(state.dt), olders, c)

    def _slide_view(self, state: PairState, older):
        """The :class:`~flowslam.sceneflow.refinement.slide.OlderView` of ``older`` (the
        :meth:`_older_view`) for the objects' slide test, with the slow-mover test's free-space
        test; None when ``slide_free_share`` is off or there is no older scan."""
        from flowslam.sceneflow.refinement.slide import OlderView

        evidence = self.options.motion_evidence
        if self.options.slide_free_share <= 0 or older is None:
            return None
        return OlderView(*older, self._scans_back(state, evidence.baseline_scans), evidence)

    def _keep_image(self, state: PairState, image) -> None:
        """Keep scan k's range ``image`` with scan k's own pose for later pairs (their older
        scans), dropping those no later pair reaches back to."""
        evidence = self.options.motion_evidence
        back = max(evidence.baseline_scans, evidence.long_baseline_scans)
        self._images = _keep_scan(self._images, state, image, state.frame.index - back - 1)

    def _slow_movers(self, state: PairState, ground, older, min_range_m: float = 0.0) -> np.ndarray:
        """:func:`~flowslam.sceneflow.refinement.visibility.slow_movers` of scan k-1 against
        ``older``, the scan ``baseline_scans`` before it (:meth:`_older_view`: placed with the
        frontend's own poses; None without one), at ``min_range_m`` or farther."""
        from flowslam.sceneflow.refinement.visibility import slow_movers

        if older is None:
            return np.zeros(len(state.prev.points), dtype=bool)
        prev_image = self._images.get(state.prev.index, (None,))[0]
        return slow_movers(state.prev.points, older[1], older[0], self.options.motion_evidence, ground, prev_image,
                           min_range_m)

    def _hidden_slow_movers(self, state: PairState, ground, older) -> np.ndarray:
        """The slow movers of scan k-1 against the scan ``hidden_baseline_scans`` before it
        (:meth:`_older_scan`), kept only at the points that ``older`` did not see
        (:func:`~flowslam.sceneflow.refinement.visibility.hidden_points`); none when the option
        is off, without ``older``, or when that scan is ``older`` itself (a run's first scans)."""
        from flowslam.sceneflow.refinement.visibility import hidden_points

        none = np.zeros(len(state.prev.points), dtype=bool)
        back = self.options.motion_evidence.hidden_baseline_scans
        newer = _placed(state, self._older_scan(state, back)) if back and older is not None else None
        if newer is None or newer[0] is older[0]:
            return none
        hidden = hidden_points(state.prev.points, older[1], older[0], self.options.motion_evidence, ground)
        return self._slow_movers(state, ground, newer) & hidden if hidden.any() else none

    def _long_slow_movers(self, state: PairState, ground) -> np.ndarray | None:
        """:func:`~flowslam.sceneflow.refinement.visibility.slow_movers` of scan k-1 against
        the scan ``long_baseline_scans`` before it, as kept from when it was scan k, at
        ``long_baseline_from_m`` or farther (horizontal range); None when the option is off
        or that scan is not kept (a run's first scans)."""
        evidence = self.options.motion_evidence
        view = self._kept_view(state, evidence.long_baseline_scans) if evidence.long_baseline_scans else None
        if view is None:
            return None
        return self._slow_movers(state, ground, view, evidence.long_baseline_from_m)

    def _older_view(self, state: PairState):
        """(range image, ``T_old_{k-1}``) of the scan ``baseline_scans`` before scan k-1
        (:meth:`_older_scan`), placed with the frontend's own poses; None without one."""
        return _placed(state, self._older_scan(state, self.options.motion_evidence.baseline_scans))

    def _kept_view(self, state: PairState, back: int):
        """(range image, ``T_old_{k-1}``) of the scan ``back`` scans before scan k-1 as kept
        from when it was scan k, placed with the frontend's own poses; None when not kept."""
        return _placed(state, self._images.get(state.prev.index - back))

    def _prev_scan(self, state: PairState) -> tuple:
        """(range image, :class:`ScanSurface` or None) of scan k-1, for the arrivals of
        :func:`~flowslam.sceneflow.refinement.visibility.geometric_movers`: as kept from when
        it was scan k; the image is built when not kept (a run's first pair)."""
        from flowslam.sceneflow.refinement.visibility import RangeImage

        image = self._images.get(state.prev.index, (None,))[0]
        if image is None:
            image = RangeImage(state.prev.points, self.options.motion_evidence)
        index, surface = self._surface
        return image, surface if index == state.prev.index else None

    def _scans_back(self, state: PairState, back: int) -> int:
        """How many scans before scan k-1 the scan :meth:`_older_scan` gives for ``back`` is
        (0: none): ``back`` when the network's window or the kept images hold it, else the
        window's oldest."""
        if back > len(state.history) - 1 and state.prev.index - back in self._images:
            return back
        return max(min(back, len(state.history) - 1), 0)

    def _older_scan(self, state: PairState, back: int):
        """(range image, own ``T_world_sensor``) of the scan ``back`` scans before scan k-1: from
        the network's window when it holds that scan (its image as kept when it was scan k,
        else built), else as kept when it was scan k (by frame index), else the window's
        oldest scan; None without an older scan (``back`` 0, or the run's first pair)."""
        from flowslam.sceneflow.refinement.visibility import RangeImage

        history = state.history  # ends with scan k-1
        back = self._scans_back(state, back)
        if back < 1:
            return None
        if back > len(history) - 1:
            return self._images[state.prev.index - back]
        old = history[-1 - back]
        image = self._images.get(old.index, (None,))[0]
        if image is None:  # a scan this stage did not see as scan k (a run's first scans, a retry)
            image = RangeImage(old.points, self.options.motion_evidence)
        return image, state.history_poses[-1 - back]


def _keep_scan(kept: dict[int, tuple], state: PairState, value, oldest: int) -> dict[int, tuple]:
    """``kept`` (frame index -> (value, its ``T_world_sensor``)) without the scans before
    frame ``oldest``, plus scan k's ``value`` with scan k's own measured pose."""
    kept = {i: v for i, v in kept.items() if i >= oldest}
    kept[state.frame.index] = (value, state.T_world_measured)
    return kept


def _placed(state: PairState, old: tuple | None):
    """(range image, ``T_old_{k-1}``) of ``old`` = (range image, own ``T_world_sensor``) of an
    older scan, placed against scan k-1 with the frontend's own poses; None for None."""
    if old is None:
        return None
    old_image, T_world_old = old
    return old_image, geometry.inv(T_world_old) @ state.history_poses[-1]


class RigidStaticFlowStage:
    """Objects off: the static points get the rigid flow of the measurement (when the
    refinement was accepted); the others keep the network's flow."""

    name = "static_flow"

    def run(self, state: PairState) -> None:
        if not state.refinement_accepted:
            return
        p, static = state.prev.points, state.static
        state.flow = state.flow.copy()
        state.flow[static] = geometry.rigid_flow(state.estimate.T_curr_prev, np.compress(static, p, axis=0))


def build_stages(config: SsfConfig, flow_odometry: FlowOdometryConfig) -> list[Stage]:
    """The stage chain for ``config`` (module doc): the network always; ``pose_start`` and
    ``refine`` when ``refine.enabled`` (and ``scan_index`` with ``objects.enabled``);
    ``flow_to_pose``; then, when ``refine.enabled``,
    ``recovery`` (which re-runs the stages before it on a faulty step) and ``objects`` (or
    ``static_flow`` with ``objects.enabled: false``)."""
    stages: list[Stage] = [NetworkStage(config)]
    if config.refine.enabled:
        stages += [PoseStartStage(config, flow_odometry), StaticRefinementStage(config)]
        if config.objects.enabled:
            stages.append(ScanIndexStage(config))
    flow_to_pose = FlowToPoseStage(flow_odometry)
    stages.append(flow_to_pose)
    if config.refine.enabled:
        recovery = MotionRecoveryStage(config, flow_to_pose)
        recovery.attach(stages)
        stages.append(recovery)
        stages.append(ObjectsStage(config) if config.objects.enabled else RigidStaticFlowStage())
    return stages
