"""The selective scan's recurrence as one compiled sequential loop (CPU float32 inference).

Same recurrence as :mod:`flowslam.sceneflow.network.selective_scan` (its module doc has
the shapes): per step ``t`` and channel ``d`` the ``S`` states decay by
``exp(max(delta_t[d] A[d, n], LOG_DECAY_FLOOR))``, take ``delta_t[d] B_t[n] x_t[d]`` and
give ``y_t[d] = sum_n C_t[n] h_t[d, n] + D[d] x_t[d]``. The chunked torch scan stores
every decay and state of the sequence (five tensors of L x Dm x S floats) and runs ~2 x
chunk small tensor operations; here the Dm x S states live in one row that is carried
from step to step, so the sequence is read once and only ``y`` is written.

The exponential is :func:`_exp_into`: ``2**n exp(r)`` with ``n`` nearest to ``z / ln 2``,
``|r| <= ln 2 / 2`` and a degree-6 Taylor polynomial (a few float32 ulp; written so
that the compiler vectorises it over the Dm x S states, as torch's own ``exp`` is).
Sums run in their own order, so ``y`` equals the chunked scan's to float32 rounding
(``tests/test_compiled_scan.py`` bounds it). Training keeps the torch scan (it has the
backward pass).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["selective_scan_compiled"]

_F = np.float32
_LOG2E = _F(1.4426950408889634)
_LN2_HI = _F(0.693359375)  # ln 2 in two parts: n * _LN2_HI is exact for |n| < 2**12
_LN2_LO = _F(-2.12194440e-4)
_ONE = _F(1.0)
_C2, _C3, _C4, _C5, _C6 = _F(1 / 2), _F(1 / 6), _F(1 / 24), _F(1 / 120), _F(1 / 720)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True, inline="always")
def _exp_into(z, out, bits, scale):
    """``out[i] = exp(z[i])`` for ``z`` in [-87, 88] (the caller clamps): ``bits`` (int32)
    and ``scale`` (its float32 view) are scratch rows of the same length."""
    for i in range(z.shape[0]):
        v = z[i]
        n = np.floor(v * _LOG2E + _F(0.5))
        r = (v - n * _LN2_HI) - n * _LN2_LO
        out[i] = _ONE + r * (_ONE + r * (_C2 + r * (_C3 + r * (_C4 + r * (_C5 + r * _C6)))))
        bits[i] = (np.int32(n) + np.int32(127)) << np.int32(23)
    for i in range(z.shape[0]):
        out[i] *= scale[i]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _scan(x, delta, A, B, C, D, floor, y):
    Bt, L, Dm = x.shape
    S = A.shape[1]
    M = Dm * S
    A_row = np.ascontiguousarray(A).reshape(M)
    h = np.empty(M, np.float32)
    z = np.empty(M, np.float32)
    a = np.empty(M, np.float32)
    u = np.empty(M, np.float32)
    bits = np.empty(M, np.int32)
    scale = bits.view(np.float32)
    for b in range(Bt):
        h[:] = 0
        for t in range(L):
            xt, dt, bt, ct = x[b, t], delta[b, t], B[b, t], C[b, t]
            for d in range(Dm):
                du = dt[d] * xt[d]
                for n in range(S):
                    z[d * S + n] = min(max(dt[d] * A_row[d * S + n], floor), _F(88.0))
                    u[d * S + n] = du * bt[n]
            _exp_into(z, a, bits, scale)
            for i in range(M):
                h[i] = a[i] * h[i] + u[i]
            yt = y[b, t]
            for d in range(Dm):
                acc = D[d] * xt[d]
                for n in range(S):
                    acc += ct[n] * h[d * S + n]
                yt[d] = acc
    return y


def selective_scan_compiled(x: np.ndarray, delta: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray,
                            D: np.ndarray, log_decay_floor: float) -> np.ndarray:
    """``y`` (Bt, L, Dm) float32 of the recurrence (module doc); inputs float32 arrays:
    ``x``, ``delta`` (Bt, L, Dm), ``A`` (Dm, S), ``B``, ``C`` (Bt, L, S), ``D`` (Dm,);
    log-decays below ``log_decay_floor`` are clamped to it."""
    arrays = [np.ascontiguousarray(v, dtype=np.float32) for v in (x, delta, A, B, C, D)]
    y = np.empty_like(arrays[0])
    return _scan(*arrays, np.float32(max(log_decay_floor, -87.0)), y)
