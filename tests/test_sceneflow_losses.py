"""Scene-adaptive loss (MambaFlow Eqs. 15-18) on hand-computed examples; DeFlow buckets; BCE."""

from __future__ import annotations

import math

import pytest
import torch

from flowslam.sceneflow.network.losses import deflow_loss, dynamic_bce, scene_adaptive_loss, scene_adaptive_split


def _along(magnitudes, seed: int = 0) -> torch.Tensor:
    """(N,3) float64 vectors of the given lengths in random directions."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(len(magnitudes), 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=1, keepdim=True) * torch.tensor(magnitudes, dtype=torch.float64).unsqueeze(1)


def test_scene_adaptive_hand_example_four_bins():
    """K = 4 so every step can be done by hand.

    |gt| = 0.10 0.15 0.20 0.30 0.35 0.45 0.60 1.00 0.05 0.12 (N = 10), r_max = 1, bins of 0.25:
      [0, .25): 0.10 0.15 0.20 0.05 0.12 -> w = 0.5
      [.25, .5): 0.30 0.35 0.45          -> w = 0.3
      [.5, .75): 0.60                    -> w = 0.1 < 1/K = 0.25  => alpha = 2, tau = 0.5
    Static: the 8 points below 0.5 m; dynamic: 0.60 and 1.00.
    With pred = 0 each EPE is |gt|: static mean 1.72 / 8 = 0.215, dynamic mean 1.6 / 2 = 0.8.
    """
    r = [0.10, 0.15, 0.20, 0.30, 0.35, 0.45, 0.60, 1.00, 0.05, 0.12]
    gt = _along(r)
    dynamic, tau, alpha = scene_adaptive_split(gt, num_bins=4)
    assert alpha == 2 and tau == pytest.approx(0.5)
    assert dynamic.tolist() == [False] * 6 + [True, True] + [False, False]
    loss = scene_adaptive_loss(torch.zeros_like(gt), gt, num_bins=4)
    assert float(loss) == pytest.approx(0.215 + 0.8, abs=1e-12)


def test_scene_adaptive_hand_example_hundred_bins():
    """K = 100: 7 static points at 0, moving points of 0.5, 0.9, 1.0 m.

    r_max = 1.0, bins of 0.01 m: bin 0 holds 7/10 >= 1/100, bin 1 is empty (0 < 1/100)
    => alpha = 1, tau = 0.01 m; static = the 7 zeros, dynamic = the 3 movers.
    Static EPEs 0.1, 0.2 and five 0 -> mean 0.3 / 7; dynamic EPEs 0.5, 0.1, 0 -> mean 0.2.
    """
    gt = _along([0.0] * 7 + [0.5, 0.9, 1.0], seed=1)
    err = _along([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.2, 0.5, 0.1, 0.0], seed=2)
    dynamic, tau, alpha = scene_adaptive_split(gt)
    assert (alpha, tau) == (1, pytest.approx(0.01))
    assert int(dynamic.sum()) == 3
    loss = scene_adaptive_loss(gt + err, gt)
    assert float(loss) == pytest.approx(0.3 / 7 + 0.2, abs=1e-12)


def test_scene_adaptive_degenerate_frames_and_gradient():
    gt = torch.zeros(5, 3, dtype=torch.float64)
    pred = _along([1.0, 2.0, 0.0, 0.0, 0.0]).requires_grad_()
    assert scene_adaptive_split(gt)[2] is None
    loss = scene_adaptive_loss(pred, gt)  # all static: the plain mean EPE
    assert float(loss.detach()) == pytest.approx(3.0 / 5)
    loss.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad[0].norm() > 0
    # NaN rows are ignored
    gt2 = _along([0.0, 0.0, 0.0, 1.0])
    gt2[0, 0] = math.nan
    assert math.isfinite(float(scene_adaptive_loss(torch.zeros_like(gt2), gt2)))


def test_deflow_buckets():
    """Speeds 0.1, 0.3 | 0.5, 1.0 | 2.0 m/s at dt = 0.1 s; pred = 0 so EPE = |gt|.

    slow mean (0.01 + 0.03) / 2 = 0.02, middle (0.05 + 0.10) / 2 = 0.075 (1.0 m/s is in the
    middle bucket), fast 0.2 -> 0.295.
    """
    gt = torch.zeros(5, 3, dtype=torch.float64)
    gt[:, 0] = torch.tensor([0.01, 0.03, 0.05, 0.10, 0.20], dtype=torch.float64)  # exactly 1.0 m/s on the edge
    assert float(deflow_loss(torch.zeros_like(gt), gt, dt=0.1)) == pytest.approx(0.295, abs=1e-12)
    # an empty bucket adds nothing
    gt = _along([0.01, 0.03])
    assert float(deflow_loss(torch.zeros_like(gt), gt)) == pytest.approx(0.02, abs=1e-12)


def test_dynamic_bce():
    logit = torch.tensor([2.0, -1.0, 0.5, 0.0], dtype=torch.float64)
    target = torch.tensor([True, False, False, True])
    sig = torch.sigmoid(logit)
    manual = -(torch.log(sig[0]) + torch.log(1 - sig[1]) + torch.log(1 - sig[2]) + torch.log(sig[3])) / 4
    assert float(dynamic_bce(logit, target)) == pytest.approx(float(manual), abs=1e-12)
    weighted = -(3 * torch.log(sig[0]) + torch.log(1 - sig[1]) + torch.log(1 - sig[2]) + 3 * torch.log(sig[3])) / 4
    assert float(dynamic_bce(logit, target, pos_weight=3.0)) == pytest.approx(float(weighted), abs=1e-12)
    mask = torch.tensor([True, True, False, False])
    manual_m = -(torch.log(sig[0]) + torch.log(1 - sig[1])) / 2
    assert float(dynamic_bce(logit, target, mask=mask)) == pytest.approx(float(manual_m), abs=1e-12)
