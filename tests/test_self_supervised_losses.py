"""Self-supervised losses of ``flowslam adapt`` (``flowslam.sceneflow.network.self_supervised``)
on hand-computed cases: rigid fits, L_mot, truncated Chamfer, L_CD, L_SC and distillation.

Most cases use the six "axis" points ``(+-a,0,0), (0,+-b,0), (0,0,+-c)``: their centroid is 0
and their covariance ``S = diag(2a^2, 2b^2, 2c^2)``, so every Kabsch fit can be done by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from flowslam.sceneflow.network.losses import scene_adaptive_loss
from flowslam.sceneflow.network.self_supervised import (
    chamfer_to_scan, distillation_loss, nearest_distance, rigid_chamfer_loss, rigid_fit, rigid_motion_loss,
    semantic_consistency_loss,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")
D = torch.float64


def _axis_points(a: float = 2.0, b: float = 1.0, c: float = 1.0) -> torch.Tensor:
    return torch.tensor([[a, 0, 0], [-a, 0, 0], [0, b, 0], [0, -b, 0], [0, 0, c], [0, 0, -c]], dtype=D)


def _rotation(rotvec, translation) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(Rotation.from_rotvec(rotvec).as_matrix(), dtype=D), torch.tensor(translation, dtype=D)


def test_rigid_fit_recovers_known_rotation_and_translation():
    src = torch.randn(20, 3, generator=torch.Generator().manual_seed(0), dtype=D) * 3
    R0, t0 = _rotation([0.3, -0.5, 1.1], [1.0, -2.0, 0.5])
    R, t = rigid_fit(src, src @ R0.T + t0)
    assert torch.allclose(R, R0, atol=1e-6) and torch.allclose(t, t0, atol=1e-6)


@pytest.mark.parametrize("mirror, expected", [
    # h = S M = diag(18, 8, -2): the reflection diag(1,1,-1) is fixed on the smallest singular value -> I.
    ((1.0, 1.0, -1.0), (1.0, 1.0, 1.0)),
    # h = diag(-18, 8, 2): unconstrained V U^T = diag(-1,1,1), fixed on the smallest -> diag(-1,1,-1).
    ((-1.0, 1.0, 1.0), (-1.0, 1.0, -1.0)),
])
def test_rigid_fit_is_a_proper_rotation_for_a_mirrored_target(mirror, expected):
    src = _axis_points(3.0, 2.0, 1.0)
    R, t = rigid_fit(src, src * torch.tensor(mirror, dtype=D))
    assert float(torch.linalg.det(R)) == pytest.approx(1.0, abs=1e-12)
    assert torch.allclose(R, torch.diag(torch.tensor(expected, dtype=D)), atol=1e-12)
    assert torch.allclose(t, torch.zeros(3, dtype=D), atol=1e-12)


def test_rigid_fit_translation_carries_gradient_rotation_does_not():
    """t = sum_i w_i dst_i / sum w - R c_src with R held fixed: d t / d dst_i = w_i / sum(w) I,
    d t / d src_i = -R w_i / sum(w)."""
    src = torch.randn(5, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    R0, t0 = _rotation([0.2, 0.1, -0.4], [0.5, 0.0, 1.0])
    dst = (src @ R0.T + t0).requires_grad_(True)
    R, t = rigid_fit(src, dst)
    assert t.requires_grad and not R.requires_grad and R.grad_fn is None
    jac = torch.autograd.functional.jacobian(lambda d: rigid_fit(src, d)[1], dst.detach())  # (3, N, 3)
    for i in range(5):
        assert torch.allclose(jac[:, i, :], torch.eye(3, dtype=D) / 5, atol=1e-12)
    w = torch.tensor([1.0, 2.0, 3.0, 0.0, 4.0], dtype=D)
    jac_w = torch.autograd.functional.jacobian(lambda d: rigid_fit(src, d, w)[1], dst.detach())
    jac_src = torch.autograd.functional.jacobian(lambda s: rigid_fit(s, dst.detach(), w)[1], src)
    for i in range(5):
        assert torch.allclose(jac_w[:, i, :], torch.eye(3, dtype=D) * w[i] / 10, atol=1e-12)
        assert torch.allclose(jac_src[:, i, :], -R0 * w[i] / 10, atol=1e-9)


def test_rigid_motion_loss_is_zero_for_one_rigid_motion_per_segment():
    g = torch.Generator().manual_seed(2)
    points = torch.randn(30, 3, generator=g, dtype=D) * 5
    segments = torch.tensor([0] * 15 + [1] * 15)
    flow = torch.empty_like(points)
    for s, (rv, tr) in enumerate([([0, 0, 0.05], [1.0, 0, 0]), ([0.1, -0.2, 0.3], [-0.5, 2.0, 0.1])]):
        R, t = _rotation(rv, tr)
        m = segments == s
        flow[m] = points[m] @ R.T + t - points[m]
    flow.requires_grad_(True)
    loss = rigid_motion_loss(points, flow, segments)
    assert loss.item() < 1e-10
    loss.backward()
    assert torch.isfinite(flow.grad).all()


def test_rigid_motion_loss_hand_value_one_radial_offset_and_ignored_points():
    """Axis points (a=2, b=c=1), flow (1,0,0) each, point (0,1,0) gets an extra e = (0,0.6,0).

    e is radial (parallel to p_k - centroid), so h = S + (p_k - c) e^T = diag(8, 2.6, 2) stays
    symmetric positive definite and the best rotation is I. Then t = mean flow = (1, 0.1, 0):
    residuals (0, 0.5, 0) on the offset point, (0, -0.1, 0) on the 5 others -> L = 1.0 / 6.
    Gradient: L = mean |r_i|, d r_i / d f_j = (delta_ij - 1/N) I, unit residuals u_k = +y,
    u_others = -y: d L / d f_k = (u_k - sum(u)/N) / N = (0, 10/36, 0).
    A 2-point segment (< min_points) and label -1 points with wild flow are ignored.
    """
    points = torch.cat([_axis_points(), torch.tensor([[9.0, 9, 9], [8, 8, 8], [5, 5, 5]], dtype=D)])
    flow = torch.tensor([[1.0, 0, 0]] * 6 + [[3.0, -1, 2], [0, 4, 0], [-7, 0, 1]], dtype=D)
    flow[2, 1] += 0.6
    segments = torch.tensor([3] * 6 + [4, 4, -1])
    flow.requires_grad_(True)
    loss = rigid_motion_loss(points, flow, segments, min_points=6)
    assert loss.item() == pytest.approx(1.0 / 6.0, abs=1e-12)
    loss.backward()
    assert torch.allclose(flow.grad[2], torch.tensor([0, 10 / 36, 0], dtype=D), atol=1e-12)
    assert torch.allclose(flow.grad[6:], torch.zeros(3, 3, dtype=D))


def test_rigid_motion_loss_without_a_large_segment_is_an_attached_zero():
    points = torch.randn(6, 3, generator=torch.Generator().manual_seed(3), dtype=D)
    flow = torch.randn(6, 3, dtype=D).requires_grad_(True)
    loss = rigid_motion_loss(points, flow, torch.tensor([-1, -1, 0, 0, 1, 1]), min_points=3)
    assert loss.item() == 0.0 and loss.requires_grad
    loss.backward()
    assert torch.equal(flow.grad, torch.zeros_like(flow))


TARGET = np.array([[0.0, 0, 0], [10, 0, 0], [0, 5, 0]])
QUERY = [[1.0, 2, 2], [10, 3, 4], [0, 5, -1]]  # nearest: origin at 3, (10,0,0) at 5, (0,5,0) at 1


@pytest.mark.parametrize("target_kind", ["numpy", "tensor", "tree"])
def test_nearest_distance_hand_values_and_unit_gradient(target_kind):
    query = torch.tensor(QUERY, dtype=D, requires_grad=True)
    if target_kind == "tree":
        d = nearest_distance(query, TARGET, tree=cKDTree(TARGET))
    else:
        target = TARGET if target_kind == "numpy" else torch.tensor(TARGET, requires_grad=True)
        d = nearest_distance(query, target)
    assert torch.allclose(d, torch.tensor([3.0, 5.0, 1.0], dtype=D), atol=1e-12)
    d.sum().backward()  # unit vector from the neighbour to the query
    assert torch.allclose(query.grad, torch.tensor([[1 / 3, 2 / 3, 2 / 3], [0, 0.6, 0.8], [0, 0, -1]], dtype=D))


def test_chamfer_to_scan_truncates_and_capped_point_has_no_gradient():
    query = torch.tensor(QUERY, dtype=D, requires_grad=True)
    loss = chamfer_to_scan(query, torch.tensor(TARGET), truncate_m=4.0)
    assert loss.item() == pytest.approx((3 + 4 + 1) / 3, abs=1e-12)
    loss.backward()
    assert torch.allclose(query.grad, torch.tensor([[1 / 9, 2 / 9, 2 / 9], [0, 0, 0], [0, 0, -1 / 3]], dtype=D))
    assert chamfer_to_scan(query, TARGET, tree=cKDTree(TARGET)).item() == pytest.approx((2 + 2 + 1) / 3)
    assert chamfer_to_scan(query[:0], TARGET).item() == 0.0


def test_rigid_chamfer_loss_zero_when_segments_move_rigidly_onto_target():
    """Each segment's flow is rigid plus n = (v, v, -v, -v, 0, 0): sum(n) = 0 and sum a_i n_i^T = 0,
    so the fit is the true motion and L_CD = 0, though the raw warped points miss the target."""
    p1, p2 = _axis_points(), _axis_points(1.5, 2.0, 0.5) + torch.tensor([20.0, 0, 0], dtype=D)
    (R1, t1), (R2, t2) = _rotation([0, 0, 0.1], [1.0, 0, 0]), _rotation([0.2, 0.1, -0.3], [0, 1.0, 0.2])
    points = torch.cat([p1, p2])
    target = torch.cat([p1 @ R1.T + t1, p2 @ R2.T + t2])
    v = torch.tensor([0.05, 0.02, -0.03], dtype=D)
    noise = torch.stack([v, v, -v, -v, 0 * v, 0 * v]).repeat(2, 1)
    flow = target - points + noise
    segments = torch.tensor([0] * 6 + [1] * 6)
    assert float(rigid_chamfer_loss(points, flow, segments, target, min_points=6)) < 1e-10
    assert float(chamfer_to_scan(points + flow, target)) > 0.02


def test_rigid_chamfer_loss_hand_value_with_truncation_and_ignored_points():
    """Segment 0: axis points translated by (1,0,0), target the same except (1,0,1) moved to (1,0,1.3):
    distances 0 x 5 and 0.3. Segment 1: the same shape 100 m away, capped at 2 each. The -1 point
    and the 2-point segment are ignored: L = (0.3 + 6 * 2) / 12 = 1.025."""
    p = _axis_points()
    points = torch.cat([p, p + torch.tensor([100.0, 0, 0], dtype=D), torch.tensor([[50.0, 50, 50]] * 3, dtype=D)])
    flow = torch.tensor([[1.0, 0, 0]] * 15, dtype=D)
    target = (p + torch.tensor([1.0, 0, 0], dtype=D)).numpy().copy()
    target[4, 2] = 1.3
    segments = torch.tensor([0] * 6 + [1] * 6 + [-1, 2, 2])
    loss = rigid_chamfer_loss(points, flow, segments, target, truncate_m=2.0, min_points=3)
    assert loss.item() == pytest.approx(12.3 / 12, abs=1e-12)
    assert float(rigid_chamfer_loss(points, flow, segments, target, min_points=7)) == 0.0


def test_semantic_consistency_loss_hand_value_and_gradients():
    """threshold 0.1 (cap 0.2), departures r = 0.05, 0.5, 0.15 -> c = 0.05, 0.2, 0.15, q = 1/2, 3/4, 1/4.
    L_i = (1-q)c + q(0.2-c) = 0.1, 0.05, 0.125 -> L = 0.275 / 3.
    d L / d logit_i = q(1-q)(2 thr - 2 c_i) / N (d/dq = -c + cap - c, c detached in the 2nd term):
    + for c < thr (descent lowers q), - for c > thr (descent raises q).
    d L / d f_i = (1 - q_i) unit(f_i - g_i) / N where r_i < cap, 0 where capped."""
    ego = torch.tensor([[0.3, -0.1, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -0.2]], dtype=D)
    unit = torch.tensor([[1.0, 0, 0], [0, 0.6, 0.8], [0, -1.0, 0]], dtype=D)
    r = torch.tensor([0.05, 0.5, 0.15], dtype=D)
    flow = (ego + r[:, None] * unit).requires_grad_(True)
    logit = torch.tensor([0.0, math.log(3), -math.log(3)], dtype=D, requires_grad=True)
    loss = semantic_consistency_loss(flow, logit, ego, threshold_m=0.1)
    assert loss.item() == pytest.approx(0.275 / 3, abs=1e-12)
    loss.backward()
    q, c = torch.tensor([0.5, 0.75, 0.25], dtype=D), torch.tensor([0.05, 0.2, 0.15], dtype=D)
    hand = q * (1 - q) * (0.2 - 2 * c) / 3
    assert torch.allclose(logit.grad, hand, atol=1e-12)
    assert logit.grad[0] > 0 and logit.grad[1] < 0 and logit.grad[2] < 0
    expected_flow_grad = ((1 - q) / 3)[:, None] * unit * torch.tensor([1.0, 0.0, 1.0], dtype=D)[:, None]
    assert torch.allclose(flow.grad, expected_flow_grad, atol=1e-12)
    # the function is smooth in the logit (the detach only matters for the flow): finite differences agree
    assert torch.autograd.gradcheck(lambda z: semantic_consistency_loss(flow.detach(), z, ego, 0.1), (logit,))


def _bce(logit: torch.Tensor, y: torch.Tensor, max_pos_weight: float = 10.0) -> torch.Tensor:
    """BCE whose positive terms weigh negatives / positives (between 1 and ``max_pos_weight``)."""
    p = torch.sigmoid(logit)
    w = min(max(1.0, float((1 - y).sum() / max(float(y.sum()), 1.0))), max_pos_weight)
    return -(w * y * torch.log(p) + (1 - y) * torch.log(1 - p)).mean()


@pytest.mark.parametrize("bce_weight", [0.2, 0.5])
def test_distillation_loss_is_scene_adaptive_plus_weighted_bce(bce_weight):
    g = torch.Generator().manual_seed(4)
    res, teacher = torch.randn(40, 3, generator=g, dtype=D), torch.randn(40, 3, generator=g, dtype=D)
    logit, dyn = torch.randn(40, generator=g, dtype=D), torch.rand(40, generator=g) < 0.3
    loss = distillation_loss(res, logit, teacher, dyn, bce_weight=bce_weight)
    expected = scene_adaptive_loss(res, teacher) + bce_weight * _bce(logit, dyn.to(D))
    assert loss.item() == pytest.approx(float(expected), abs=1e-12)


@pytest.mark.parametrize("max_pos_weight, weight", [(10.0, 10.0), (4.0, 4.0), (1.0, 1.0), (50.0, 39.0)])
def test_distillation_bce_weighs_rare_dynamic_points_up(max_pos_weight, weight):
    logit, dyn = torch.zeros(40, dtype=D), torch.zeros(40, dtype=torch.bool)
    dyn[3] = True  # 1 dynamic point of 40: negatives / positives = 39
    flow = torch.zeros(40, 3, dtype=D)
    loss = distillation_loss(flow, logit, flow, dyn, bce_weight=1.0, max_pos_weight=max_pos_weight)
    # every term is log 2 (logit 0): (39 + weight) * log 2 / 40
    assert loss.item() == pytest.approx((39 + weight) * np.log(2) / 40, abs=1e-12)


@pytest.mark.parametrize("calibrated, optimum_share", [(False, 0.5), (True, 0.1)])
def test_calibrated_distillation_bce_is_minimised_at_the_share_of_dynamic_points(calibrated, optimum_share):
    # 10 dynamic points of 100: the positive terms weigh 90 / 10 = 9. One logit z for every point:
    # the weighted BCE 9 * 10 * -log q + 90 * -log(1 - q) is least at q = 0.5 (9 times the odds of
    # the share 0.1); with the logit shifted by log 9 inside the loss, at q = 0.1 (the share itself)
    dyn = torch.arange(100) < 10
    flow = torch.zeros(100, 3, dtype=D)

    def loss(z: float) -> float:
        logit = torch.full((100,), z, dtype=D)
        return distillation_loss(flow, logit, flow, dyn, bce_weight=1.0, calibrated=calibrated).item()

    best = np.log(optimum_share / (1 - optimum_share))
    assert loss(best) < min(loss(best - 0.05), loss(best + 0.05))
    shifted = best - np.log(9) if not calibrated else best + np.log(9)  # where the other loss is least
    assert loss(best) < loss(shifted) - 0.01


def test_distillation_loss_mask_restricts_to_masked_rows():
    g = torch.Generator().manual_seed(5)
    res = torch.randn(30, 3, generator=g, dtype=D).requires_grad_(True)
    teacher, logit = torch.randn(30, 3, generator=g, dtype=D), torch.randn(30, generator=g, dtype=D)
    dyn, mask = torch.rand(30, generator=g) < 0.4, torch.arange(30) % 3 != 0
    loss = distillation_loss(res, logit, teacher, dyn, mask=mask)
    expected = scene_adaptive_loss(res[mask], teacher[mask]) + 0.2 * _bce(logit[mask], dyn[mask].to(D))
    assert loss.item() == pytest.approx(expected.item(), abs=1e-12)
    loss.backward()
    assert torch.equal(res.grad[~mask], torch.zeros(10, 3, dtype=D)) and res.grad[mask].abs().sum() > 0
    wild, wild_logit = teacher.clone(), logit.clone()
    wild[~mask], wild_logit[~mask] = 1e3, -50.0  # unmasked rows changed: loss unchanged
    assert distillation_loss(res, wild_logit, wild, dyn, mask=mask).item() == pytest.approx(loss.item(), abs=1e-12)
