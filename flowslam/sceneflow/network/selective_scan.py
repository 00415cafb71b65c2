"""Mamba's S6 selective scan in pure PyTorch: chunked two-pass scan with a custom backward.

The recurrence (diagonal ``A``; one independent state vector per channel ``d``)::

    h_t[d, n] = exp(delta_t[d] * A[d, n]) * h_{t-1}[d, n] + delta_t[d] * B_t[n] * x_t[d]
    y_t[d]    = sum_n C_t[n] * h_t[d, n] + D[d] * x_t[d]                    (h_{-1} = 0)

Shapes: ``x, delta`` (Bt, L, Dm); ``A`` (Dm, S), negative for a decaying state;
``B, C`` (Bt, L, S); ``D`` (Dm,). ``delta`` must already be positive (the caller
applies softplus). All quantities are unitless; in flowslam the sequence axis is
the Z-order of the points of one scan (see ``flowssm.py``).

How it avoids a length-L Python loop
------------------------------------
The sequence is cut into ``nc`` chunks of ``chunk`` steps (zero-padded at the end:
``delta = 0`` gives decay 1 and input 0) and laid out *step-major*, (Bt, chunk, nc, ...),
so one step of every chunk is one contiguous slice.

1. *Local pass*: every chunk is scanned from a zero state at once, one chunk step
   per Python iteration; only the chunk-final states are kept.
2. *Carry*: the state entering chunk ``c`` follows the same linear recurrence over
   chunks, ``carry_c = P_{c-1} carry_{c-1} + hend_{c-1}``, where the chunk's total
   decay ``P_c = exp(A * sum_chunk(delta))`` comes from a log-space sum, clamped
   at ``LOG_DECAY_FLOOR``. Long carry sequences recurse into ``linear_scan``.
3. *Final pass*: every chunk is scanned again from its carry, keeping each state.

A scan of length L costs about ``2 * chunk + L / chunk`` Python iterations (~500
for L = 32k, chunk 128) instead of L. Every decay is ``exp`` of a non-positive
number clamped at -60, so float32 can neither overflow nor produce denormals (no
``exp(+cumsum)`` rescaling tricks are needed).

Backward (``SelectiveScanFn.backward``) recomputes the states with the same passes
and runs the adjoint recurrence ``dh_t = a_{t+1} dh_{t+1} + g_t C_t`` backwards in
the same chunked way (a reverse carry over chunks); every parameter gradient is then
one vectorised reduction. ``selective_scan_reference`` is the plain sequential loop
with autograd, the oracle of the tests.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["selective_scan", "selective_scan_reference", "linear_scan", "SelectiveScanFn"]

LOG_DECAY_FLOOR = -60.0
"""Log-decays are clamped here (exp(-60) ~ 9e-27: numerically a full reset, never a denormal)."""


# ---------------------------------------------------------------------------- layout
def _n_chunks(L: int, chunk: int) -> tuple[int, int]:
    chunk = max(1, min(int(chunk), L))
    return chunk, -(-L // chunk)


def _to_chunks(t: Tensor, chunk: int, nc: int) -> Tensor:
    """(Bt, L, ...) -> step-major (Bt, chunk, nc, ...), zero-padded at the end.

    Padding only ever follows the last real step, so it cannot change any real state.
    """
    Bt, L = t.shape[:2]
    pad = chunk * nc - L
    if pad:
        t = torch.cat([t, t.new_zeros((Bt, pad) + t.shape[2:])], 1)
    return t.reshape((Bt, nc, chunk) + t.shape[2:]).transpose(1, 2).contiguous()


def _from_chunks(t: Tensor, L: int) -> Tensor:
    """Step-major (Bt, chunk, nc, ...) -> (Bt, L, ...)."""
    Bt, chunk, nc = t.shape[:3]
    return t.transpose(1, 2).reshape((Bt, chunk * nc) + t.shape[3:])[:, :L]


# ---------------------------------------------------------------------------- loops
def _scan_forward(a: Tensor, u: Tensor, h0: Tensor | None, store: bool) -> Tensor:
    """``h_t = a_t h_{t-1} + u_t`` along dim 1 of step-major tensors, from ``h0`` (or 0).

    Returns all states (shape of ``u``) when ``store``, else the last state (Bt, nc, ...).
    """
    K = u.shape[1]
    h = u[:, 0] if h0 is None else torch.addcmul(u[:, 0], a[:, 0], h0)
    if not store:
        for t in range(1, K):
            h = torch.addcmul(u[:, t], a[:, t], h)
        return h
    out = torch.empty_like(u)
    out[:, 0] = h
    for t in range(1, K):
        torch.addcmul(u[:, t], a[:, t], out[:, t - 1], out=out[:, t])
    return out


def _scan_backward(a: Tensor, v: Tensor, k0: Tensor | None, store: bool) -> Tensor:
    """Adjoint ``g_t = a_{t+1} g_{t+1} + v_t`` along dim 1, backwards, with ``g_top = v_top + k0``.

    Returns all adjoints when ``store``, else the adjoint at step 0 (Bt, nc, ...).
    """
    K = v.shape[1]
    g = v[:, K - 1] if k0 is None else v[:, K - 1] + k0
    if not store:
        for t in range(K - 2, -1, -1):
            g = torch.addcmul(v[:, t], a[:, t + 1], g)
        return g
    out = torch.empty_like(v)
    out[:, K - 1] = g
    for t in range(K - 2, -1, -1):
        torch.addcmul(v[:, t], a[:, t + 1], out[:, t + 1], out=out[:, t])
    return out


def _decay_(log_decay: Tensor) -> Tensor:
    """``exp`` of log-decays clamped at ``LOG_DECAY_FLOOR``, in place (pass a temporary)."""
    return log_decay.clamp_(min=LOG_DECAY_FLOOR).exp_()


def linear_scan(a: Tensor, u: Tensor, chunk: int = 128) -> Tensor:
    """All states of ``h_t = a_t h_{t-1} + u_t`` (h_{-1} = 0) along dim 1 of (Bt, L, ...) tensors.

    ``a`` are decays in [0, 1]. Chunked as described in the module doc (used for the
    carries between chunks, and usable on its own).
    """
    L = u.shape[1]
    if L == 0:
        return u.clone()
    chunk, nc = _n_chunks(L, chunk)
    a_c = _to_chunks(a, chunk, nc)  # padded steps sit after the last real one: never used
    u_c = _to_chunks(u, chunk, nc)
    if nc == 1:
        return _from_chunks(_scan_forward(a_c, u_c, None, True), L)
    h_end = _scan_forward(a_c, u_c, None, False)
    p_chunk = _decay_(torch.log(a_c).sum(1))  # log-space product: no underflow to denormals
    carries = linear_scan(p_chunk[:, :-1], h_end[:, :-1], chunk)
    h0 = torch.cat([torch.zeros_like(h_end[:, :1]), carries], 1)
    return _from_chunks(_scan_forward(a_c, u_c, h0, True), L)


# ---------------------------------------------------------------------------- S6
class _Chunked:
    """The step-major views of one scan's inputs, and its per-step decays/inputs."""

    def __init__(self, x: Tensor, delta: Tensor, A: Tensor, B: Tensor, chunk: int):
        self.L = x.shape[1]
        self.chunk, self.nc = _n_chunks(self.L, chunk)
        self.x = _to_chunks(x, self.chunk, self.nc)  # (Bt, K, nc, Dm)
        self.delta = _to_chunks(delta, self.chunk, self.nc)  # padded steps: delta 0 -> decay 1
        self.B = _to_chunks(B, self.chunk, self.nc)  # (Bt, K, nc, S)
        self.A = A
        # per-step decays a = exp(delta A) and inputs u = delta x B, (Bt, K, nc, Dm, S)
        self.a = _decay_(self.delta.unsqueeze(-1) * A)
        self.u = (self.delta * self.x).unsqueeze(-1) * self.B.unsqueeze(3)
        # log-space sum of each chunk's step sizes -> total chunk decay (Bt, nc, Dm, S)
        self.p_chunk = _decay_(self.delta.sum(1).unsqueeze(-1) * A)

    def states(self) -> Tensor:
        """All states (Bt, K, nc, Dm, S)."""
        if self.nc == 1:
            return _scan_forward(self.a, self.u, None, True)
        h_end = _scan_forward(self.a, self.u, None, False)  # chunk-local final states
        carries = linear_scan(self.p_chunk[:, :-1], h_end[:, :-1], self.chunk)
        h0 = torch.cat([torch.zeros_like(h_end[:, :1]), carries], 1)
        return _scan_forward(self.a, self.u, h0, True)

    def adjoints(self, v: Tensor) -> Tensor:
        """All adjoint states ``dh`` for per-step injections ``v`` (Bt, K, nc, Dm, S)."""
        if self.nc == 1:
            return _scan_backward(self.a, v, None, True)
        g_start = _scan_backward(self.a, v, None, False)  # (Bt, nc, Dm, S), zero carry
        # carry into the top of chunk c: k_c = a0_{c+1} g_{c+1}(start) with the true carry,
        # i.e. k_c = P_{c+1} k_{c+1} + a0_{c+1} g_start_{c+1}: a scan over chunks, reversed
        coef = self.p_chunk[:, 1:].flip(1)
        inp = (self.a[:, 0, 1:] * g_start[:, 1:]).flip(1)
        k = linear_scan(coef, inp, self.chunk).flip(1)
        k = torch.cat([k, torch.zeros_like(k[:, :1])], 1)
        return _scan_backward(self.a, v, k, True)


class SelectiveScanFn(torch.autograd.Function):
    """Chunked selective scan with a hand-written backward (see module doc)."""

    @staticmethod
    def forward(ctx, x, delta, A, B, C, D, chunk: int):  # type: ignore[override]
        ch = _Chunked(x, delta, A, B, chunk)
        H = ch.states()
        C_c = _to_chunks(C, ch.chunk, ch.nc)
        y = torch.matmul(H, C_c.unsqueeze(-1)).squeeze(-1)  # (Bt, K, nc, Dm)
        y = _from_chunks(y, ch.L) + x * D
        ctx.save_for_backward(x, delta, A, B, C, D)
        ctx.chunk = chunk
        return y

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        x, delta, A, B, C, D = ctx.saved_tensors
        ch = _Chunked(x, delta, A, B, ctx.chunk)
        H = ch.states()
        C_c = _to_chunks(C, ch.chunk, ch.nc)
        g_c = _to_chunks(g.contiguous(), ch.chunk, ch.nc)  # (Bt, K, nc, Dm)
        dH = ch.adjoints(g_c.unsqueeze(-1) * C_c.unsqueeze(3))
        # a_t h_{t-1} = h_t - u_t: the gradient w.r.t. log a_t is dh_t * (h_t - u_t)
        q = ch.u.neg_().add_(H).mul_(dH)
        r = torch.matmul(dH, ch.B.unsqueeze(-1)).squeeze(-1)  # sum_n dh B      (Bt,K,nc,Dm)
        dx = _from_chunks(ch.delta * r, ch.L) + g * D
        qA = (q * A).sum(-1)  # sum_n q A                                      (Bt,K,nc,Dm)
        ddelta = _from_chunks(ch.x * r + qA, ch.L)
        dA = torch.einsum("bkcdn,bkcd->dn", q, ch.delta)
        dB = _from_chunks(torch.einsum("bkcdn,bkcd->bkcn", dH, ch.delta * ch.x), ch.L)
        dC = _from_chunks(torch.einsum("bkcd,bkcdn->bkcn", g_c, H), ch.L)
        dD = (g * x).sum((0, 1))
        return dx, ddelta, dA, dB, dC, dD, None


# ---------------------------------------------------------------------------- API
def _check(x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor) -> None:
    if x.dim() != 3 or delta.shape != x.shape:
        raise ValueError(f"x and delta must be (Bt, L, Dm), got {tuple(x.shape)} and {tuple(delta.shape)}")
    Bt, L, Dm = x.shape
    if A.dim() != 2 or A.shape[0] != Dm:
        raise ValueError(f"A must be (Dm={Dm}, S), got {tuple(A.shape)}")
    S = A.shape[1]
    for name, t in (("B", B), ("C", C)):
        if tuple(t.shape) != (Bt, L, S):
            raise ValueError(f"{name} must be {(Bt, L, S)}, got {tuple(t.shape)}")
    if tuple(D.shape) != (Dm,):
        raise ValueError(f"D must be ({Dm},), got {tuple(D.shape)}")


def _autocast_on(device_type: str) -> bool:
    """Whether autocast is on for ``device_type`` (torch < 2.4 takes no device type)."""
    try:
        return torch.is_autocast_enabled(device_type)
    except TypeError:
        return torch.is_autocast_cpu_enabled() if device_type == "cpu" else torch.is_autocast_enabled()


COMPILED_INFERENCE = True
"""Whether CPU float32 inference (no autograd) scans with
:func:`~flowslam.sceneflow.network.compiled_scan.selective_scan_compiled` (one compiled
sequential loop, ~6x faster on the ``tiny`` decoder) instead of the chunked torch scan."""


def _compiled_applies(inputs: tuple[Tensor, ...]) -> bool:
    """Whether the compiled scan serves these inputs: CPU float32, no autograd, no autocast."""
    return (not torch.is_grad_enabled() and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in inputs)
            and not _autocast_on("cpu"))


def selective_scan(
    x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor, chunk: int = 128
) -> Tensor:
    """Chunked selective scan ``y`` (Bt, L, Dm); see the module doc for the recurrence and shapes.

    ``chunk`` trades Python iterations (``2 * chunk``) against the carry length
    (``L / chunk``); ~sqrt(L) is best on CPU, larger on GPU. Half-precision inputs are
    scanned in float32 (as Mamba's kernels do) and the result is cast back. CPU float32
    inference takes the compiled loop (``COMPILED_INFERENCE``; ``chunk`` is then unused).
    """
    _check(x, delta, A, B, C, D)
    if x.shape[1] == 0:
        return x.clone()
    inputs = (x, delta, A, B, C, D)
    if COMPILED_INFERENCE and _compiled_applies(inputs):
        from flowslam.sceneflow.network.compiled_scan import selective_scan_compiled

        return torch.from_numpy(selective_scan_compiled(*(t.detach().numpy() for t in inputs), LOG_DECAY_FLOOR))
    if any(t.dtype in (torch.float16, torch.bfloat16) for t in inputs) or _autocast_on(x.device.type):
        # mixed precision (autocast hands over some inputs in half precision): the scan and its
        # hand-written backward run in float32, with autocast off so that no matmul drops back
        with torch.autocast(x.device.type, enabled=False):
            y = SelectiveScanFn.apply(*(t.float() for t in inputs), int(chunk))
        return y.to(x.dtype)
    return SelectiveScanFn.apply(x, delta, A, B, C, D, int(chunk))


def selective_scan_reference(x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor) -> Tensor:
    """The same recurrence as a plain sequential loop over L (autograd; slow, for tests)."""
    _check(x, delta, A, B, C, D)
    Bt, L, Dm = x.shape
    h = x.new_zeros(Bt, Dm, A.shape[1])
    ys = []
    for t in range(L):
        a = torch.exp(delta[:, t, :, None] * A)
        h = a * h + (delta[:, t] * x[:, t])[:, :, None] * B[:, t, None, :]
        ys.append((h * C[:, t, None, :]).sum(-1) + D * x[:, t])
    return torch.stack(ys, 1)
