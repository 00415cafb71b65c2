"""Self-supervised losses of ``flowslam adapt``: no labels, only the scans themselves and
the ``ssf`` pipeline's own (teacher) flow and segmentation.

Every function takes torch tensors; lengths are metres, flows metres per frame. The
convention is the interface's: a source point ``p`` of scan k-1 (its own sensor frame),
its flow ``f`` (Argoverse 2: ``p + f`` is the same physical point in sensor frame k),
``target`` the points of scan k (sensor frame k). ``segments`` is an (N,) integer
labelling of the source points into rigid parts: ``-1`` for points that belong to none,
``0`` for the static world, ``1..K`` for moving instances (SSF-PAN's M_t^(s), M_t^(d)).

The three segmentation losses follow the names of SSF-PAN's Table VI (the paper gives
no equations; these are our definitions, after the OGC losses it builds on):

- ``rigid_motion_loss`` (L_mot): every segment moves rigidly: each point's flow should
  equal the rigid motion fitted to its segment's flow.
- ``semantic_consistency_loss`` (L_SC): segmentation and flow agree: a point labelled
  static follows the ego motion, a point whose flow departs from the ego motion is
  labelled dynamic.
- ``rigid_chamfer_loss`` (L_CD): the source moved segment by segment with the fitted
  rigid motions lands on scan k (truncated one-way Chamfer distance).

Plus the data term ``chamfer_to_scan`` (each warped point lands on scan k) and
``distillation_loss`` (the network's flow and dynamic logit against the teacher's).

Rigid fits (``rigid_fit``): weighted Kabsch; the rotation is fitted on detached values
(no gradient through the SVD, whose derivative is unstable for the near-degenerate
covariances of thin objects) and the translation ``t = mean(p + f) - R mean(p)`` keeps
the gradient, so the losses pull each flow towards its segment's rigid motion.
Nearest neighbours are found with a KD-tree on detached values; the distance to the
neighbour found keeps the gradient.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from flowslam.sceneflow.network.losses import dynamic_bce, scene_adaptive_loss

__all__ = [
    "rigid_fit", "rigid_motion_loss", "rigid_chamfer_loss", "semantic_consistency_loss", "chamfer_to_scan",
    "nearest_distance", "distillation_loss",
]


def rigid_fit(src: Tensor, dst: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Weighted least-squares rigid motion ``dst ~ R src + t`` of (N,3) point sets.

    Returns ``(R, t)``: R (3,3) detached (Kabsch on detached values, a proper rotation),
    t (3,) differentiable with respect to ``dst`` (and ``weights``). N >= 3 non-collinear
    points give a unique R; fewer give the best one SVD finds.
    """
    w = torch.ones(len(src), dtype=src.dtype, device=src.device) if weights is None else weights
    w = w / w.sum().clamp_min(1e-12)
    c_src = (w[:, None] * src).sum(0)
    c_dst = (w[:, None] * dst).sum(0)
    with torch.no_grad():
        h = ((src - c_src) * w[:, None]).T @ (dst.detach() - c_dst.detach())
        u, _, vt = torch.linalg.svd(h.double())
        d = torch.sign(torch.linalg.det(vt.T @ u.T))
        fix = torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d]))
        R = (vt.T @ fix @ u.T).to(src.dtype)
    return R, c_dst - R @ c_src


def _segment_rigid_flow(points: Tensor, flow: Tensor, segments: Tensor, min_points: int) -> tuple[Tensor, Tensor]:
    """(rigid flow of each point's segment, mask of the points in a segment of >= min_points)."""
    rigid = torch.zeros_like(flow)
    used = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    for s in torch.unique(segments):
        if s < 0:
            continue
        m = segments == s
        if int(m.sum()) < min_points:
            continue
        p = points[m]
        R, t = rigid_fit(p, p + flow[m])
        rigid[m] = p @ R.T + t - p
        used |= m
    return rigid, used


def rigid_motion_loss(points: Tensor, flow: Tensor, segments: Tensor, min_points: int = 10) -> Tensor:
    """L_mot: mean over the points of segments with >= ``min_points`` points of
    ``|| f_i - (R_s p_i + t_s - p_i) ||``, (R_s, t_s) the rigid fit of segment s's flow
    (``rigid_fit``). 0 for a flow that is rigid per segment; 0 (attached) when no
    segment is large enough."""
    rigid, used = _segment_rigid_flow(points, flow, segments, min_points)
    if not used.any():
        return flow.sum() * 0.0
    return torch.linalg.vector_norm(flow[used] - rigid[used], dim=1).mean()


def nearest_distance(query: Tensor, target: np.ndarray | Tensor, tree: cKDTree | None = None) -> Tensor:
    """(N,) Euclidean distance of each query point to its nearest point of ``target``
    (M,3), differentiable with respect to ``query``; the neighbour is found on detached
    values (``tree``: a prebuilt ``cKDTree`` of ``target``)."""
    target_np = target.detach().cpu().numpy() if isinstance(target, Tensor) else np.asarray(target)
    tree = tree if tree is not None else cKDTree(target_np)
    _, idx = tree.query(query.detach().cpu().double().numpy(), k=1)
    nearest = torch.as_tensor(target_np[idx], dtype=query.dtype, device=query.device)
    return torch.linalg.vector_norm(query - nearest, dim=1)


def chamfer_to_scan(warped: Tensor, target: np.ndarray | Tensor, truncate_m: float = 2.0,
                    tree: cKDTree | None = None) -> Tensor:
    """Data term: mean over the warped source points (``p + f``, sensor frame k) of the
    distance to the nearest point of scan k, each distance capped at ``truncate_m`` (a
    point with no counterpart, e.g. newly occluded, then adds a constant and no
    gradient). One-way: scan k's points need no source."""
    if len(warped) == 0:
        return warped.sum()
    return nearest_distance(warped, target, tree).clamp(max=truncate_m).mean()


def rigid_chamfer_loss(points: Tensor, flow: Tensor, segments: Tensor, target: np.ndarray | Tensor,
                       truncate_m: float = 2.0, min_points: int = 10, tree: cKDTree | None = None) -> Tensor:
    """L_CD: ``chamfer_to_scan`` of the source moved by each segment's rigid fit
    (``p + rigid flow``), over the points of segments with >= ``min_points`` points."""
    rigid, used = _segment_rigid_flow(points, flow, segments, min_points)
    if not used.any():
        return flow.sum() * 0.0
    return chamfer_to_scan(points[used] + rigid[used], target, truncate_m, tree)


def semantic_consistency_loss(flow: Tensor, dynamic_logit: Tensor, ego_flow: Tensor,
                              threshold_m: float = 0.1) -> Tensor:
    """L_SC: the dynamic probability and the flow agree.

    With ``r_i = || f_i - g_i ||`` the departure of the flow from the ego motion's flow
    ``g`` (a static point's flow, ``T_{k,k-1} p - p``, from the system's own estimate),
    ``c_i = min(r_i, 2 threshold)`` and ``q_i = sigmoid(logit_i)``:

        L_SC = mean_i [ (1 - q_i) c_i + q_i (2 threshold - c_i.detach()) ]

    A point called static is pulled onto the ego motion (first term). The gradient on
    ``q_i`` is ``2 threshold - 2 c_i`` (on the logit, times ``q_i (1 - q_i) > 0``, the
    same sign): descent raises the probability where the flow departs from the ego
    motion by more than ``threshold_m`` and lowers it where it departs by less.
    """
    cap = 2.0 * threshold_m
    c = torch.linalg.vector_norm(flow - ego_flow, dim=1).clamp(max=cap)
    q = torch.sigmoid(dynamic_logit)
    if len(q) == 0:
        return q.sum()
    return ((1.0 - q) * c + q * (cap - c.detach())).mean()


def distillation_loss(residual: Tensor, dynamic_logit: Tensor, teacher_residual: Tensor, teacher_dynamic: Tensor,
                      mask: Tensor | None = None, bce_weight: float = 0.2, max_pos_weight: float = 10.0,
                      calibrated: bool = False) -> Tensor:
    """The network against the teacher (the refined ``ssf`` pipeline): MambaFlow's
    scene-adaptive loss on the residual flow plus ``bce_weight`` x BCE of the dynamic
    logit against the teacher's dynamic labels, over ``mask`` (e.g. the points inside
    the network's grid). The BCE's positive (dynamic) terms weigh ``negatives /
    positives`` of the sample, at most ``max_pos_weight`` (1: plain BCE): on real scans
    well under 1 % of the points move, and a plain BCE teaches the head to call nothing
    dynamic.

    A weight ``w`` on the positive terms moves the BCE's minimiser to the true log-odds
    plus ``log w``: the head then calls points dynamic at ``w`` times lower odds than a
    plainly trained head, whose threshold the pipeline keeps. ``calibrated`` adds ``log w``
    to the logit inside the loss (logit adjustment), so that the minimiser is the true
    log-odds again while the positive terms keep their weight."""
    if mask is not None:
        residual, teacher_residual = residual[mask], teacher_residual[mask]
        dynamic_logit, teacher_dynamic = dynamic_logit[mask], teacher_dynamic[mask]
    flow_term = scene_adaptive_loss(residual, teacher_residual)
    positives = float(teacher_dynamic.sum())
    pos_weight = min(max(1.0, (len(teacher_dynamic) - positives) / max(positives, 1.0)), max_pos_weight)
    logit = dynamic_logit + math.log(pos_weight) if calibrated else dynamic_logit
    return flow_term + bce_weight * dynamic_bce(logit, teacher_dynamic, pos_weight=pos_weight)
