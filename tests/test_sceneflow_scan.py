"""The chunked selective scan against the sequential reference: values and gradients."""

from __future__ import annotations

import time

import pytest
import torch

from flowslam.sceneflow.network.selective_scan import linear_scan, selective_scan, selective_scan_reference


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _inputs(Bt: int, L: int, Dm: int, S: int, dtype=torch.float32, seed: int = 0, dt_scale: float = 1.0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(Bt, L, Dm, generator=g, dtype=dtype)
    delta = torch.nn.functional.softplus(torch.randn(Bt, L, Dm, generator=g, dtype=dtype)) * dt_scale
    A = -torch.rand(Dm, S, generator=g, dtype=dtype) * 3 - 0.05
    B = torch.randn(Bt, L, S, generator=g, dtype=dtype)
    C = torch.randn(Bt, L, S, generator=g, dtype=dtype)
    D = torch.randn(Dm, generator=g, dtype=dtype)
    return [t.requires_grad_() for t in (x, delta, A, B, C, D)]


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / (b.abs().max() + 1e-12))


@pytest.mark.parametrize(
    "L,chunk",
    [(1, 64), (37, 64), (64, 64), (200, 64), (257, 128), (300, 16), (777, 7), (1000, 256)],
)
def test_values_and_gradients_match_reference_float32(L, chunk):
    """Lengths that are and are not multiples of the chunk; 777/7 recurses into the carry scan."""
    ins = _inputs(2, L, 5, 4, seed=L)
    y = selective_scan(*ins, chunk=chunk)
    y_ref = selective_scan_reference(*ins)
    assert y.shape == y_ref.shape == (2, L, 5)
    assert _rel_err(y, y_ref) < 2e-5
    w = torch.randn(y.shape, generator=torch.Generator().manual_seed(1))
    grads = torch.autograd.grad((y * w).sum(), ins)
    grads_ref = torch.autograd.grad((y_ref * w).sum(), ins)
    for name, g, gr in zip(("x", "delta", "A", "B", "C", "D"), grads, grads_ref):
        assert _rel_err(g, gr) < 2e-5, name


def test_mixed_precision_inputs_under_autocast_scan_and_backpropagate_in_float32():
    """Autocast (bf16 training on a GPU) hands over some inputs in bf16 and others in float32:
    the scan and its hand-written backward run in float32 (an earlier version failed in the
    backward with 'expected scalar type Float but found BFloat16')."""
    ins = _inputs(2, 300, 5, 4, seed=3)
    mixed = [t.detach().to(torch.bfloat16).requires_grad_() if i in (3, 4) else t for i, t in enumerate(ins)]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = selective_scan(*mixed, chunk=64)
    rounded = [t.detach().float().requires_grad_() for t in mixed]  # the same values, all float32
    y_ref = selective_scan_reference(*rounded)
    assert y.dtype == torch.float32 and _rel_err(y, y_ref) < 2e-5
    grads = torch.autograd.grad(y.sum(), mixed)
    grads_ref = torch.autograd.grad(y_ref.sum(), rounded)
    for name, g, gr in zip(("x", "delta", "A", "B", "C", "D"), grads, grads_ref):
        assert g.dtype == mixed["x delta A B C D".split().index(name)].dtype, name
        assert _rel_err(g.float(), gr) < 1e-2, name  # bf16 gradients of B and C


def test_gradients_exact_in_float64():
    ins = _inputs(1, 150, 3, 2, dtype=torch.float64, seed=3)
    y = selective_scan(*ins, chunk=32)
    y_ref = selective_scan_reference(*ins)
    assert _rel_err(y, y_ref) < 1e-12
    for g, gr in zip(torch.autograd.grad(y.sum(), ins), torch.autograd.grad(y_ref.sum(), ins)):
        assert _rel_err(g, gr) < 1e-12


def test_gradcheck_small():
    ins = [t.detach().requires_grad_() for t in _inputs(1, 11, 2, 3, dtype=torch.float64, seed=5)]
    assert torch.autograd.gradcheck(lambda *a: selective_scan(*a, chunk=4), ins, eps=1e-6, atol=1e-6)


def test_stable_with_strong_decay_and_long_sequence():
    """Large steps (decays underflow to the clamp) and a 20k sequence stay finite and exact."""
    ins = _inputs(1, 20000, 4, 3, seed=7, dt_scale=30.0)
    y = selective_scan(*ins, chunk=128)
    assert torch.isfinite(y).all()
    ref = selective_scan_reference(*[t.detach()[:, :500] if t.dim() == 3 else t.detach() for t in ins])
    assert _rel_err(y[:, :500].detach(), ref) < 2e-5
    y.sum().backward()
    assert all(torch.isfinite(t.grad).all() for t in ins)


def test_linear_scan_matches_cumulative_recurrence():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 500, 2, generator=g, dtype=torch.float64)
    u = torch.randn(3, 500, 2, generator=g, dtype=torch.float64)
    h = torch.zeros(3, 2, dtype=torch.float64)
    ref = []
    for t in range(500):
        h = a[:, t] * h + u[:, t]
        ref.append(h)
    assert _rel_err(linear_scan(a, u, chunk=9), torch.stack(ref, 1)) < 1e-12


def test_speed_chunked_vs_sequential(capsys, monkeypatch):
    """Printed, not asserted: the chunked scan and the compiled inference loop against the
    sequential reference."""
    from flowslam.sceneflow.network import selective_scan as module

    L, Dm, S = 4096, 16, 8
    ins = [t.detach() for t in _inputs(1, L, Dm, S, seed=9, dt_scale=0.1)]
    times = {}
    with torch.no_grad():
        for name, compiled in (("chunked", False), ("compiled", True)):
            monkeypatch.setattr(module, "COMPILED_INFERENCE", compiled)
            selective_scan(*ins, chunk=64)  # warm-up
            t0 = time.perf_counter()
            selective_scan(*ins, chunk=64)
            times[name] = time.perf_counter() - t0
        t0 = time.perf_counter()
        selective_scan_reference(*ins)
        sequential = time.perf_counter() - t0
    with capsys.disabled():
        print(f"\nselective scan L={L} Dm={Dm} S={S}: chunked {1e3 * times['chunked']:.1f} ms, "
              f"compiled {1e3 * times['compiled']:.1f} ms, sequential {1e3 * sequential:.1f} ms "
              f"({sequential / max(times['chunked'], 1e-9):.0f}x the chunked)")
