"""The compiled selective scan (CPU float32 inference) against the chunked torch scan and
the sequential reference; the vectorised exponential it uses; when ``selective_scan``
takes it. Real torch and numba, no mocks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowslam.sceneflow.network import selective_scan as module
from flowslam.sceneflow.network.compiled_scan import _exp_into, selective_scan_compiled
from flowslam.sceneflow.network.selective_scan import LOG_DECAY_FLOOR, selective_scan, selective_scan_reference

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _inputs(Bt: int, L: int, Dm: int, S: int, seed: int = 0, dt_scale: float = 1.0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(Bt, L, Dm, generator=g)
    delta = torch.nn.functional.softplus(torch.randn(Bt, L, Dm, generator=g)) * dt_scale
    A = -torch.rand(Dm, S, generator=g) * 3 - 0.05
    B = torch.randn(Bt, L, S, generator=g)
    C = torch.randn(Bt, L, S, generator=g)
    D = torch.randn(Dm, generator=g)
    return [x, delta, A, B, C, D]


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / (b.abs().max() + 1e-12))


@pytest.mark.parametrize("Bt, L, Dm, S", [(1, 1, 3, 2), (2, 37, 5, 4), (1, 777, 16, 8), (2, 300, 32, 16)])
def test_compiled_scan_equals_the_reference_and_the_chunked_scan(Bt, L, Dm, S):
    ins = _inputs(Bt, L, Dm, S, seed=L)
    y = torch.from_numpy(selective_scan_compiled(*(t.numpy() for t in ins), LOG_DECAY_FLOOR))
    assert y.shape == (Bt, L, Dm) and y.dtype == torch.float32
    assert _rel_err(y, selective_scan_reference(*ins)) < 2e-5
    with torch.no_grad():
        module_chunked = module.SelectiveScanFn.apply(*ins, 64)
    assert _rel_err(y, module_chunked) < 2e-5


def test_compiled_scan_stays_finite_where_decays_reach_the_floor():
    """Huge steps: every log-decay below LOG_DECAY_FLOOR is clamped there, as the chunked
    scan does (a full reset each step), so both give the same finite numbers."""
    ins = _inputs(1, 2000, 4, 3, seed=7, dt_scale=60.0)
    y = torch.from_numpy(selective_scan_compiled(*(t.numpy() for t in ins), LOG_DECAY_FLOOR))
    assert torch.isfinite(y).all()
    with torch.no_grad():
        assert _rel_err(y, module.SelectiveScanFn.apply(*ins, 128)) < 2e-5


def test_vectorised_exp_is_within_a_few_ulp():
    z = np.linspace(-87.0, 88.0, 200_001).astype(np.float32)
    out = np.empty_like(z)
    bits = np.empty(len(z), np.int32)
    _exp_into(z, out, bits, bits.view(np.float32))
    exact = np.exp(z.astype(np.float64))
    assert np.max(np.abs(out / exact - 1.0)) < 4 * np.finfo(np.float32).eps


def test_selective_scan_takes_the_compiled_loop_only_for_cpu_float32_inference(monkeypatch):
    ins = _inputs(1, 50, 4, 3, seed=1)
    calls = []
    real = module._compiled_applies
    monkeypatch.setattr(module, "_compiled_applies", lambda inputs: calls.append(real(inputs)) or calls[-1])
    with torch.no_grad():
        y = selective_scan(*ins, chunk=16)
    assert calls == [True] and not y.requires_grad
    trainable = [t.clone().requires_grad_() for t in ins]
    y = selective_scan(*trainable, chunk=16)  # autograd on: the chunked scan and its backward
    assert calls == [True, False] and y.requires_grad
    y.sum().backward()
    assert all(t.grad is not None for t in trainable)
    with torch.no_grad():
        y64 = selective_scan(*(t.double() for t in ins), chunk=16)  # float64: the torch scan
    assert calls[-1] is False and y64.dtype == torch.float64
