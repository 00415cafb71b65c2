"""Scene-flow evaluation of a frontend in pipeline conditions (``flowslam flow-eval``).

The frontend runs over the sequence through the same frame loop as ``flowslam run``
(``run_pipeline``: its own ego prior, no GT); a :class:`FlowEvaluation` sink compares
every per-point flow it returns (for scan k-1, Argoverse 2 convention) with the
dataset's GT flow. Also reported: the ego-motion error of its odometry against the GT
relative poses, and the reference method ``ego-gt`` ("perfect odometry, objects
static": flow = the true ego motion), whose error is all in the moving objects.

Labels come from the reader: ``Frame.extras["av2_category"]`` (Argoverse 2 category
index per point) and ``Frame.extras["is_ground"]``; a reader without them counts every
point as background, not ground.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from flowslam import geometry
from flowslam.config import PipelineConfig
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput
from flowslam.sceneflow.metrics import av2_eval_mask, flow_metrics


class _Accumulator:
    def __init__(self):
        self.parts: dict[str, list] = {k: [] for k in
                                       ("pred", "gt", "dynamic", "classes", "ground", "points", "ego", "pred_dyn")}

    def add(self, **arrays):
        for k, v in arrays.items():
            self.parts[k].append(v)

    def metrics(self, dt: float) -> dict:
        cat = {k: np.concatenate(v) if v else None for k, v in self.parts.items()}
        if cat["pred"] is None:
            return {}
        return flow_metrics(
            cat["pred"], cat["gt"], cat["dynamic"], cat["classes"], cat["ground"], cat["points"], dt,
            ego_flow=cat["ego"], pred_dynamic=cat["pred_dyn"],
        )


def frame_labels(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """Argoverse 2 category index and ground mask of every point (zeros / False when the
    reader gives none)."""
    n = len(frame.points)
    classes = frame.extras.get("av2_category")
    ground = frame.extras.get("is_ground")
    return (np.zeros(n, np.int64) if classes is None else np.asarray(classes, np.int64),
            np.zeros(n, bool) if ground is None else np.asarray(ground, bool))


class FlowEvaluation:
    """Output sink of ``run_pipeline``: flow metrics of a frontend's outputs and of
    ``ego-gt``, and its ego-motion error (translation m, rotation deg per step).

    ``gt_poses`` are the dataset's ``T_world_sensor`` by dataset index; ``scored``, when
    given, the dataset indices of the newest scans of the only pairs to score; ``flow``:
    False keeps only the ego-motion error and the moving-object metrics (``objects``), not
    the per-point flow arrays the flow metrics are computed from (long runs: memory).
    """

    def __init__(self, gt_poses: np.ndarray, scored: set[int] | None = None, flow: bool = True):
        from flowslam.moving_objects import MovingObjectsLog
        from flowslam.sceneflow.object_metrics import ObjectScores

        self.gt_poses = gt_poses
        self.scored = scored
        self.flow = flow
        self.method, self.reference = _Accumulator(), _Accumulator()
        self.objects = ObjectScores()
        self.objects_in_region = ObjectScores()
        """The same metrics on the points the flow metrics score (AV2's evaluation region:
        non-ground, within the close box): the objects of those points only."""
        self._tracks = MovingObjectsLog()  # the method's objects with track ids, as ``flowslam run`` logs them
        self.ego_t: list[float] = []
        self.ego_r: list[float] = []
        self.dts: list[float] = []
        self._prev: Frame | None = None

    def on_output(self, frame: Frame, out: FrontendOutput) -> None:
        prev, self._prev = self._prev, frame
        logged = len(self._tracks.objects)
        self._tracks.on_output(frame, out)
        if prev is None or prev.gt_flow is None or (self.scored is not None and frame.index not in self.scored):
            return
        T_curr_prev = geometry.relative(self.gt_poses[frame.index], self.gt_poses[prev.index])
        ego = geometry.rigid_flow(T_curr_prev, prev.points)
        classes, ground = frame_labels(prev)
        dynamic = np.zeros(len(prev.points), bool) if prev.gt_dynamic is None else prev.gt_dynamic
        common = dict(gt=prev.gt_flow, dynamic=dynamic, classes=classes, ground=ground, points=prev.points, ego=ego)
        if self.flow:
            self.reference.add(pred=ego, pred_dyn=np.zeros(len(ego), bool), **common)
        if out.flow is not None and self.flow:
            pred_dyn = np.zeros(len(ego), bool) if out.static_mask is None else ~np.asarray(out.static_mask, bool)
            self.method.add(pred=out.flow, pred_dyn=pred_dyn, **common)
        if out.T_prev_curr is not None:
            E = geometry.inv(geometry.relative(self.gt_poses[prev.index], self.gt_poses[frame.index])) @ out.T_prev_curr
            self.ego_t.append(float(geometry.translation_norm(E)))
            self.ego_r.append(float(np.degrees(geometry.rotation_angle(E))))
        self.dts.append(frame.timestamp - prev.timestamp)
        if prev.gt_instance is not None and out.instance_ids is not None and out.static_mask is not None:
            self._score_objects(prev, out, T_curr_prev, self.dts[-1], self._tracks.objects[logged:],
                                av2_eval_mask(prev.points, ground))

    def _score_objects(self, prev: Frame, out: FrontendOutput, T_curr_prev: np.ndarray, dt: float,
                       logged: list, region: np.ndarray) -> None:
        """Instance metrics of the pair (:mod:`flowslam.sceneflow.object_metrics`); ``dt`` (s);
        ``region`` (N,) bool: the points of scan k-1 the flow metrics score."""
        from flowslam.moving_objects import moving_objects

        gt_dynamic = np.asarray(prev.gt_dynamic, bool)
        gt = np.where(gt_dynamic, prev.gt_instance, -1)
        pred = np.where(np.asarray(out.static_mask, bool), -1, out.instance_ids)
        truth = moving_objects(prev.points, prev.gt_flow, prev.gt_instance, geometry.inv(T_curr_prev), dt, ~gt_dynamic)
        velocity = {o.instance_id: o.velocity for o in logged}
        gt_velocity = {o.instance_id: o.velocity for o in truth}
        track = {o.instance_id: o.track_id for o in logged}
        self.objects.add(pred, gt, velocity, gt_velocity, track)
        self.objects_in_region.add(np.where(region, pred, -1), np.where(region, gt, -1), velocity, gt_velocity, track)

    def result(self, frontend_name: str) -> dict:
        """Every metric, JSON-serialisable."""
        dt = float(np.median(self.dts)) if self.dts else 0.1
        t, r = self.ego_t, self.ego_r
        return {
            "frontend": frontend_name,
            "pairs": len(self.dts),
            "flow": self.method.metrics(dt),
            "ego-gt reference": self.reference.metrics(dt),
            "objects": self.objects.result() if self.objects.pairs else None,
            "objects_in_region": self.objects_in_region.result() if self.objects_in_region.pairs else None,
            "ego_motion_error": {
                "trans_m_mean": float(np.mean(t)) if t else None,
                "trans_m_rmse": float(np.sqrt(np.mean(np.square(t)))) if t else None,
                "rot_deg_mean": float(np.mean(r)) if r else None,
            },
        }


def evaluate_flow(
    path,
    config: PipelineConfig,
    *,
    on_start: Callable[[int], None] | None = None,
    on_frame: Callable[[int, float], None] | None = None,
    frontend=None,
    skip_pairs: int = 0,
) -> dict:
    """Run ``config.frontend`` (or the given ``frontend`` instance) with ``config.backend``
    over the sequence at ``path`` (opened with ``config.dataset``, frames from
    ``dataset.first_frame`` / ``max_frames``) and return :meth:`FlowEvaluation.result`,
    with ``skipped_pairs``. Every frame runs; with ``skip_pairs`` N the first N scan pairs
    are not scored (a warm-up: ``ssf``'s slow-mover test needs a scan ~0.7 s older than
    scan k-1, so its first pairs see no slow movers).

    Raises ``InputError`` when the sequence has no GT poses or ``skip_pairs`` leaves no
    pair to score, and re-raises the error that stopped the loop, if any.
    """
    from flowslam.datasets import frame_range, open_dataset
    from flowslam.errors import InputError
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend

    dataset = open_dataset(path, config.dataset)
    if dataset.gt_poses is None:
        raise InputError(path, "flow-eval needs GT poses and GT flow")
    frames = frame_range(len(dataset), config.dataset)
    if skip_pairs < 0 or skip_pairs >= len(frames) - 1:
        raise InputError("--skip-pairs", f"{skip_pairs} leaves no pair to score: the {len(frames)} frames make "
                         f"{max(len(frames) - 1, 0)} pairs (use 0 to {max(len(frames) - 2, 0)})")
    frontend = frontend or make_frontend(config.frontend, config)
    scored = set(frames[skip_pairs + 1:]) if skip_pairs else None  # the newer scan of each scored pair
    sink = FlowEvaluation(np.asarray(dataset.gt_poses), scored=scored)
    if on_start is not None:
        on_start(len(frames))
    result = run_pipeline(dataset, frontend, make_backend(config.backend, config), frames, on_frame,
                          on_output=sink.on_output)
    if result.error is not None:
        raise result.error
    return {**sink.result(getattr(frontend, "name", config.frontend)), "skipped_pairs": skip_pairs}
