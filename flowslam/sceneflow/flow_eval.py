"""Scene-flow evaluation of a frontend in pipeline conditions (``flowslam flow-eval``).

The frontend runs over the sequence exactly as in ``flowslam run`` (its own ego prior,
no GT); every per-point flow it returns (for scan k-1, Argoverse 2 convention) is
compared with the dataset's GT flow. Also reported: the ego-motion error of its
odometry against the GT relative poses, and the reference method ``ego-gt``
("perfect odometry, objects static": flow = the true ego motion), whose error is all
in the moving objects.

Labels: Argoverse 2 logs carry AV2 categories and ``is_ground``; simulated sequences
are mapped (``simulated_to_av2``): car -> REGULAR_VEHICLE, truck -> TRUCK, cyclist ->
BICYCLIST, pedestrian -> PEDESTRIAN, everything else background; road, sidewalk and
terrain are ground.
"""

from __future__ import annotations

import time

import numpy as np

from flowslam import geometry
from flowslam.datasets.frame import Dataset, Frame
from flowslam.sceneflow.metrics import AV2_CATEGORIES, flow_metrics

_SIM_TO_AV2 = {"car": "REGULAR_VEHICLE", "truck": "TRUCK", "cyclist": "BICYCLIST", "pedestrian": "PEDESTRIAN"}
_SIM_GROUND = ("road", "sidewalk", "terrain")


def simulated_to_av2(classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(AV2 category index per point, is_ground) for simulator class ids."""
    from flowslam.simulation.labels import CLASS_NAMES

    lut = np.zeros(max(CLASS_NAMES) + 1, dtype=np.int64)
    ground = np.zeros(max(CLASS_NAMES) + 1, dtype=bool)
    for cid, name in CLASS_NAMES.items():
        if name in _SIM_TO_AV2:
            lut[cid] = AV2_CATEGORIES.index(_SIM_TO_AV2[name])
        ground[cid] = name in _SIM_GROUND
    c = np.asarray(classes, dtype=np.int64)
    return lut[c], ground[c]


def frame_labels(dataset: Dataset, frame: Frame) -> tuple[np.ndarray, np.ndarray | None]:
    """AV2-style classes and ground mask of a frame (zeros / None when unknown)."""
    n = len(frame.points)
    if frame.gt_class is None:
        return np.zeros(n, np.int64), None
    if dataset.name == "simulated":
        return simulated_to_av2(frame.gt_class)
    return np.asarray(frame.gt_class), frame.extras.get("is_ground")


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


def evaluate_flow(dataset: Dataset, frontend, frames: range, on_frame=None) -> dict:
    """Run ``frontend`` over ``frames``; flow metrics of its outputs and of ``ego-gt``, plus
    its ego-motion error (translation m, rotation deg per step) against the GT poses."""
    if dataset.gt_poses is None:
        raise ValueError("flow evaluation needs GT poses")
    method, reference = _Accumulator(), _Accumulator()
    ego_t, ego_r = [], []
    prev: Frame | None = None
    dts = []
    for k, index in enumerate(frames):
        start = time.perf_counter()
        frame = dataset[index]
        out = frontend.process(frame)
        if prev is not None and prev.gt_flow is not None:
            T_curr_prev = geometry.relative(dataset.gt_poses[index], dataset.gt_poses[prev.index])
            ego = geometry.transform_points(T_curr_prev, prev.points) - prev.points
            classes, ground = frame_labels(dataset, prev)
            ground = np.zeros(len(prev.points), bool) if ground is None else ground
            dynamic = np.zeros(len(prev.points), bool) if prev.gt_dynamic is None else prev.gt_dynamic
            common = dict(gt=prev.gt_flow, dynamic=dynamic, classes=classes, ground=ground,
                          points=prev.points, ego=ego)
            reference.add(pred=ego, pred_dyn=np.zeros(len(ego), bool), **common)
            if out.flow is not None:
                pred_dyn = None if out.static_mask is None else ~np.asarray(out.static_mask, bool)
                method.add(pred=out.flow, pred_dyn=pred_dyn if pred_dyn is not None else np.zeros(len(ego), bool),
                           **common)
            if out.T_prev_curr is not None:
                E = geometry.inv(geometry.relative(dataset.gt_poses[prev.index], dataset.gt_poses[index])) @ out.T_prev_curr
                ego_t.append(float(geometry.translation_norm(E)))
                ego_r.append(float(np.degrees(geometry.rotation_angle(E))))
            dts.append(frame.timestamp - prev.timestamp)
        prev = frame
        if on_frame is not None:
            on_frame(k, time.perf_counter() - start)
    dt = float(np.median(dts)) if dts else 0.1
    return {
        "frontend": getattr(frontend, "name", "?"),
        "pairs": len(dts),
        "flow": method.metrics(dt),
        "ego-gt reference": reference.metrics(dt),
        "ego_motion_error": {
            "trans_m_mean": float(np.mean(ego_t)) if ego_t else None,
            "trans_m_rmse": float(np.sqrt(np.mean(np.square(ego_t)))) if ego_t else None,
            "rot_deg_mean": float(np.mean(ego_r)) if ego_r else None,
        },
    }
