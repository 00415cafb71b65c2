"""Training losses for scene flow: MambaFlow's scene-adaptive loss, DeFlow's 3-bucket loss, BCE.

All flows are (N, 3) tensors in metres per frame. Train on the *residual* flow (the
network's output against ``gt_flow - ego_flow``, both in the newest sensor frame), as
MambaFlow and DeFlow do: then a point's flow magnitude is its own motion in the world.
Rows with a NaN/inf in ``pred`` or ``gt`` are ignored.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["scene_adaptive_split", "scene_adaptive_loss", "deflow_loss", "dynamic_bce", "DEFLOW_SPEED_BUCKETS"]

DEFLOW_SPEED_BUCKETS = (0.4, 1.0)
"""DeFlow's bucket edges in m/s: [0, 0.4), [0.4, 1.0], (1.0, inf)."""


def _finite(pred: Tensor, gt: Tensor) -> tuple[Tensor, Tensor]:
    if pred.shape != gt.shape or pred.dim() != 2 or pred.shape[1] != 3:
        raise ValueError(f"pred and gt must both be (N, 3), got {tuple(pred.shape)} and {tuple(gt.shape)}")
    ok = torch.isfinite(pred).all(1) & torch.isfinite(gt).all(1)
    if ok.all():
        return pred, gt
    return pred[ok], gt[ok]


def _mean_or_zero(x: Tensor) -> Tensor:
    return x.mean() if x.numel() else x.sum()  # empty part: 0, still attached to the graph


def scene_adaptive_split(gt: Tensor, num_bins: int = 100) -> tuple[Tensor, float, int | None]:
    """MambaFlow's static/dynamic split of one frame (Eqs. 15-17, see ``scene_adaptive_loss``).

    Returns ``(dynamic, tau, alpha)``: the (N,) bool mask of the dynamic points (bin
    index >= alpha, i.e. ``||gt|| >= tau``), the threshold ``tau`` on the GT flow
    magnitude (m) and the 0-based index ``alpha`` of the first sparse bin; ``(all
    False, inf, None)`` when no bin is sparse or every GT flow is zero.
    """
    r = torch.linalg.vector_norm(gt.detach(), dim=-1).double()
    none = torch.zeros(r.shape, dtype=torch.bool, device=r.device)
    if r.numel() == 0:
        return none, float("inf"), None
    r_max = float(r.max())
    if r_max <= 0.0:
        return none, float("inf"), None
    width = r_max / num_bins
    j = torch.clamp((r / width).floor().long(), max=num_bins - 1)  # bin of each point, last bin closed
    w = torch.bincount(j, minlength=num_bins).double() / r.numel()
    sparse = torch.nonzero(w < 1.0 / num_bins)
    if sparse.numel() == 0:
        return none, float("inf"), None
    alpha = int(sparse[0, 0])
    return j >= alpha, alpha * width, alpha


def scene_adaptive_loss(pred: Tensor, gt: Tensor, num_bins: int = 100) -> Tensor:
    """MambaFlow's scene-adaptive loss (paper Eqs. 15-18), in our words.

    1. (Eq. 15) Take each point's GT flow magnitude ``r_i = ||gt_i||`` (m; using speeds
       instead changes nothing, every quantity below scales with it) and cut
       ``[0, r_max]`` into ``K = num_bins`` equal bins of width ``r_max / K``.
    2. (Eq. 16) The weight of bin ``j`` is the fraction of points in it,
       ``w_j = n_j / N`` (the last bin includes ``r_max``).
    3. (Eq. 17) ``alpha`` is the first bin whose weight falls below the uniform share,
       ``w_alpha < 1 / K``: the bulk of (near-)static points is behind it. The split
       threshold is that bin's lower edge, ``tau = alpha * r_max / K``: points with
       ``r < tau`` are static, ``r >= tau`` dynamic.
    4. (Eq. 18) The loss is the mean end-point error of the static points plus the
       mean end-point error of the dynamic points (an empty part adds 0), so the few
       moving points weigh as much as the many static ones whatever the scene.

    The split is recomputed for every call (i.e. per frame: call it per sample).
    Degenerate frames (all GT zero, or no sparse bin) are all static: the loss is the
    plain mean EPE. The split carries no gradient. (MambaFlow's released training code
    differs from the paper: it bins speeds over [min, max], splits at the sparse bin's
    centre and adds a third bucket above 2 m/s; this follows the paper.)

    Args:
        pred, gt: (N, 3) predicted and GT (residual) flow, metres.
        num_bins: K.
    """
    pred, gt = _finite(pred, gt)
    epe = torch.linalg.vector_norm(pred - gt, dim=-1)
    dynamic, _, _ = scene_adaptive_split(gt, num_bins)
    return _mean_or_zero(epe[~dynamic]) + _mean_or_zero(epe[dynamic])


def deflow_loss(
    pred: Tensor, gt: Tensor, dt: float = 0.1, buckets: tuple[float, float] = DEFLOW_SPEED_BUCKETS
) -> Tensor:
    """DeFlow's loss: mean EPE in each of three GT-speed buckets, summed (empty buckets add 0).

    Speed is ``||gt|| / dt`` (m/s) with the frame interval ``dt`` (s); buckets are
    ``[0, 0.4)``, ``[0.4, 1.0]`` and ``(1.0, inf)`` m/s by default.
    """
    pred, gt = _finite(pred, gt)
    epe = torch.linalg.vector_norm(pred - gt, dim=-1)
    speed = torch.linalg.vector_norm(gt.detach(), dim=-1) / dt
    lo, hi = buckets
    slow = speed < lo
    fast = speed > hi
    mid = ~slow & ~fast
    return _mean_or_zero(epe[slow]) + _mean_or_zero(epe[mid]) + _mean_or_zero(epe[fast])


def dynamic_bce(logit: Tensor, target: Tensor, pos_weight: float | None = None, mask: Tensor | None = None) -> Tensor:
    """Binary cross-entropy of the dynamic head (mean over the points, or over ``mask``).

    ``target``: (N,) bool/float, 1 = the point moves in the world. ``pos_weight`` scales
    the positive terms (moving points are rare).
    """
    target = target.to(logit.dtype)
    if mask is not None:
        logit, target = logit[mask], target[mask]
    if logit.numel() == 0:
        return logit.sum()
    pw = None if pos_weight is None else torch.as_tensor(pos_weight, dtype=logit.dtype, device=logit.device)
    return F.binary_cross_entropy_with_logits(logit, target, pos_weight=pw)
