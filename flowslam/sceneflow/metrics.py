"""Scene-flow metrics as pure numpy functions (Argoverse 2 / OpenSceneFlow definitions).

Inputs are (N,3) flows in metres per frame in the Argoverse 2 convention (``p + flow``
is the point at t+1 in the sensor frame of t+1) unless a function says *residual*
(flow minus the ego-motion flow ``T_{t+1,t} p - p``). ``points`` are the source scan's
points in its own sensor frame (m). ``classes`` are Argoverse 2 category indices
(``AV2_CATEGORIES``; 0 = background / no box).

Definitions
-----------
- EPE3D: mean end-point error ``||pred - gt||`` (m).
- AccStrict / AccRelax: fraction of points with EPE < 0.05 m *or* relative error
  ``EPE / ||gt||`` < 5 % (0.1 m / 10 % for Relax), as in the AV2 evaluation.
- Outliers: fraction with EPE > 0.3 m *or* relative error > 10 % (FlowNet3D's
  Outliers3D).
- Dynamic: a point whose residual flow is at least 0.5 m/s (AV2: 0.05 m per 0.1 s
  sweep; ``dt`` is the nominal frame interval).
- 3-way EPE (AV2 2023 leaderboard): points that are not ground and lie in the
  70 m x 70 m box ``|x|, |y| <= 35`` m around the ego vehicle; foreground = any
  annotated class; EPE_FD (foreground dynamic), EPE_FS (foreground static),
  EPE_BS (background static); their plain average is the 3-way EPE (a part without
  points is NaN and left out of the average).
- Bucketed normalised EPE (AV2 2024, "I Can't Believe It's Not Scene Flow!", as in
  OpenSceneFlow): on *residual* flows of non-ground points within 35 m (xy radius).
  Meta-classes ``BUCKET_CLASSES``; speed buckets of 0.4 m/s from 0 to 20 m/s plus one
  open bucket. Static EPE of a class = mean EPE of its points below 0.4 m/s (for
  BACKGROUND: of all its points); dynamic error of a class = mean over its non-empty
  faster buckets of (mean EPE / mean GT residual flow magnitude), unitless. "Mean"
  averages the classes (NaN-skipping). To score a sequence, concatenate the frames'
  arrays: bucket means are then point-weighted over the sequence, as in the benchmark.
- Dynamic IoU: TP / (TP + FP + FN) of the predicted vs. GT dynamic masks.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "AV2_CATEGORIES",
    "BUCKET_CLASSES",
    "class_indices",
    "end_point_error",
    "epe3d",
    "acc_strict",
    "acc_relax",
    "outliers",
    "dynamic_from_flow",
    "av2_eval_mask",
    "three_way_epe",
    "bucketed_epe",
    "dynamic_iou",
    "flow_metrics",
]

AV2_CATEGORIES: tuple[str, ...] = (
    "NONE", "ANIMAL", "ARTICULATED_BUS", "BICYCLE", "BICYCLIST", "BOLLARD", "BOX_TRUCK", "BUS",
    "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE", "DOG", "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER", "PEDESTRIAN",
    "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS", "SIGN", "STOP_SIGN", "STROLLER",
    "TRAFFIC_LIGHT_TRAILER", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "WHEELCHAIR", "WHEELED_DEVICE",
    "WHEELED_RIDER",
)
"""Argoverse 2 sensor-dataset category of each class index (0 = no annotation)."""

BUCKET_CLASSES: dict[str, tuple[str, ...]] = {
    "BACKGROUND": ("NONE",),
    "CAR": ("REGULAR_VEHICLE",),
    "OTHER_VEHICLES": (
        "BOX_TRUCK", "LARGE_VEHICLE", "RAILED_VEHICLE", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER",
        "ARTICULATED_BUS", "BUS", "SCHOOL_BUS",
    ),
    "PEDESTRIAN": ("PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"),
    "WHEELED_VRU": ("BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE", "WHEELED_RIDER"),
}
"""Meta-classes of the bucketed evaluation (other categories, e.g. signs, are not scored)."""

DYNAMIC_SPEED = 0.5  # m/s
CLOSE_BOX = 35.0  # m
STRICT = 0.05
RELAX = 0.1
OUTLIER_EPE, OUTLIER_REL = 0.3, 0.1
BUCKET_SPEED_EDGES = np.concatenate([np.linspace(0.0, 20.0, 51), [np.inf]])  # m/s
_EPS = 1e-10


def class_indices(names: tuple[str, ...]) -> np.ndarray:
    """AV2 class indices of category names."""
    return np.array([AV2_CATEGORIES.index(n) for n in names], dtype=np.int64)


def end_point_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(N,) per-point EPE (m)."""
    return np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(gt, np.float64), axis=-1)


def _rel(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e = end_point_error(pred, gt)
    return e, e / (np.linalg.norm(np.asarray(gt, np.float64), axis=-1) + _EPS)


def _mean(x: np.ndarray) -> float:
    return float(np.mean(x)) if x.size else float("nan")


def epe3d(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean EPE (m); NaN for no points."""
    return _mean(end_point_error(pred, gt))


def acc_strict(pred: np.ndarray, gt: np.ndarray) -> float:
    """Fraction with EPE < 0.05 m or relative error < 5 %."""
    e, r = _rel(pred, gt)
    return _mean(((e < STRICT) | (r < STRICT)).astype(np.float64))


def acc_relax(pred: np.ndarray, gt: np.ndarray) -> float:
    """Fraction with EPE < 0.1 m or relative error < 10 %."""
    e, r = _rel(pred, gt)
    return _mean(((e < RELAX) | (r < RELAX)).astype(np.float64))


def outliers(pred: np.ndarray, gt: np.ndarray) -> float:
    """Fraction with EPE > 0.3 m or relative error > 10 %."""
    e, r = _rel(pred, gt)
    return _mean(((e > OUTLIER_EPE) | (r > OUTLIER_REL)).astype(np.float64))


def dynamic_from_flow(
    flow: np.ndarray, ego_flow: np.ndarray, dt: float = 0.1, threshold: float = DYNAMIC_SPEED
) -> np.ndarray:
    """(N,) bool: residual speed ``||flow - ego_flow|| / dt >= threshold`` (m/s)."""
    return end_point_error(flow, ego_flow) / dt >= threshold


def av2_eval_mask(points: np.ndarray, is_ground: np.ndarray | None, box: float = CLOSE_BOX) -> np.ndarray:
    """(N,) bool: not ground and within ``|x|, |y| <= box`` (m) of the sensor."""
    p = np.asarray(points)
    m = (np.abs(p[:, 0]) <= box) & (np.abs(p[:, 1]) <= box)
    return m if is_ground is None else m & ~np.asarray(is_ground, bool)


def three_way_epe(
    pred: np.ndarray,
    gt: np.ndarray,
    dynamic: np.ndarray,
    classes: np.ndarray,
    is_ground: np.ndarray | None,
    points: np.ndarray,
    box: float = CLOSE_BOX,
) -> dict[str, float]:
    """AV2's 3-way EPE (m) with the part sizes; see the module doc."""
    e = end_point_error(pred, gt)
    m = av2_eval_mask(points, is_ground, box)
    dyn = np.asarray(dynamic, bool)
    fg = np.asarray(classes) != 0
    parts = {"EPE_FD": m & fg & dyn, "EPE_FS": m & fg & ~dyn, "EPE_BS": m & ~fg & ~dyn}
    out = {k: _mean(e[v]) for k, v in parts.items()}
    vals = [v for v in out.values() if np.isfinite(v)]
    out["EPE_3way"] = float(np.mean(vals)) if vals else float("nan")
    out.update({f"count_{k[4:]}": int(v.sum()) for k, v in parts.items()})
    return out


def bucketed_epe(
    pred_residual: np.ndarray,
    gt_residual: np.ndarray,
    classes: np.ndarray,
    mask: np.ndarray | None = None,
    dt: float = 0.1,
) -> dict[str, dict[str, float]]:
    """Bucketed normalised EPE on residual flows: ``{class: {"static", "dynamic"}}`` plus "Mean"."""
    e = end_point_error(pred_residual, gt_residual)
    mag = np.linalg.norm(np.asarray(gt_residual, np.float64), axis=-1)
    speed = mag / dt
    cls = np.asarray(classes)
    keep = np.ones(len(e), bool) if mask is None else np.asarray(mask, bool)
    bucket = np.searchsorted(BUCKET_SPEED_EDGES, speed, side="right") - 1  # bucket k: [edge_k, edge_k+1)
    out: dict[str, dict[str, float]] = {}
    for name, cats in BUCKET_CLASSES.items():
        in_cls = keep & np.isin(cls, class_indices(cats))
        if name == "BACKGROUND":
            out[name] = {"static": _mean(e[in_cls]), "dynamic": float("nan")}
            continue
        static = _mean(e[in_cls & (bucket == 0)])
        ratios = []
        for k in np.unique(bucket[in_cls & (bucket > 0)]):
            sel = in_cls & (bucket == k)
            ratios.append(e[sel].mean() / mag[sel].mean())
        out[name] = {"static": static, "dynamic": float(np.mean(ratios)) if ratios else float("nan")}
    with np.errstate(all="ignore"):
        stat = [v["static"] for v in out.values() if np.isfinite(v["static"])]
        dyn = [v["dynamic"] for v in out.values() if np.isfinite(v["dynamic"])]
    out["Mean"] = {
        "static": float(np.mean(stat)) if stat else float("nan"),
        "dynamic": float(np.mean(dyn)) if dyn else float("nan"),
    }
    return out


def dynamic_iou(pred_dynamic: np.ndarray, gt_dynamic: np.ndarray, mask: np.ndarray | None = None) -> float:
    """TP / (TP + FP + FN) of two bool masks (NaN when both are empty)."""
    p, g = np.asarray(pred_dynamic, bool), np.asarray(gt_dynamic, bool)
    if mask is not None:
        p, g = p[mask], g[mask]
    tp = np.sum(p & g)
    denom = tp + np.sum(p & ~g) + np.sum(~p & g)
    return float(tp / denom) if denom else float("nan")


def segmentation_accuracy(pred_dynamic: np.ndarray, gt_dynamic: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SSA: the share of points whose static/dynamic label is right (NaN without points).
    SSF-PAN (Table VI) reports an SSA without defining it; this is the plain per-point
    accuracy of the binary motion segmentation, so it is dominated by the static points
    (a segmentation that calls everything static scores the static share)."""
    p, g = np.asarray(pred_dynamic, bool), np.asarray(gt_dynamic, bool)
    if mask is not None:
        p, g = p[mask], g[mask]
    return float(np.mean(p == g)) if len(p) else float("nan")


def flow_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    dynamic: np.ndarray,
    classes: np.ndarray,
    is_ground: np.ndarray | None,
    points: np.ndarray,
    dt: float = 0.1,
    ego_flow: np.ndarray | None = None,
    pred_dynamic: np.ndarray | None = None,
) -> dict:
    """All metrics of one frame (or of concatenated frames) as a flat dict.

    EPE3D / AccStrict / AccRelax / Outliers and the 3-way EPE are computed on the AV2
    evaluation points (not ground, ``|x|, |y| <= 35`` m). The bucketed EPE needs
    ``ego_flow`` (the true ego-motion flow, to form residuals); Dynamic IoU and SSA need
    ``pred_dynamic`` or ``ego_flow`` (then a point is predicted dynamic when its predicted
    residual speed is at least 0.5 m/s). Keys missing their inputs are left out.
    """
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    m = av2_eval_mask(points, is_ground)
    out: dict = {
        "EPE3D": epe3d(pred[m], gt[m]),
        "AccStrict": acc_strict(pred[m], gt[m]),
        "AccRelax": acc_relax(pred[m], gt[m]),
        "Outliers": outliers(pred[m], gt[m]),
        "num_points": int(m.sum()),
    }
    out.update(three_way_epe(pred, gt, dynamic, classes, is_ground, points))
    if pred_dynamic is None and ego_flow is not None:
        pred_dynamic = dynamic_from_flow(pred, ego_flow, dt)
    if pred_dynamic is not None:
        out["DynamicIoU"] = dynamic_iou(pred_dynamic, dynamic, m)
        out["SSA"] = segmentation_accuracy(pred_dynamic, dynamic, m)
    if ego_flow is not None:
        ego = np.asarray(ego_flow, np.float64)
        p = np.asarray(points)
        near = np.hypot(p[:, 0], p[:, 1]) <= CLOSE_BOX
        if is_ground is not None:
            near &= ~np.asarray(is_ground, bool)
        buck = bucketed_epe(pred - ego, gt - ego, classes, near, dt)
        for cls, v in buck.items():
            out[f"bucketed/{cls}/static"] = v["static"]
            out[f"bucketed/{cls}/dynamic"] = v["dynamic"]
    return out
