"""The separable STDCB's temporal branches, Soft Feature Selection pooling and Temporal
Gated Block as two compiled passes (CPU float32 inference).

Same block as :class:`flowslam.sceneflow.network.backbone.STDCB` with ``separable=True``
and its BatchNorms folded (its docstring and the module doc of ``backbone`` have the
structure). Between the pointwise expansion and the projection the torch form runs ~9
kernels, each a pass over a (B, T, H, W, C) tensor that does not fit in the cache (5 x 128
x 128 x 16 floats at the finest level): two temporal depthwise convolutions, three means,
the branch weighting (three passes), the gate's convolution with its sigmoid and the
product. oneDNN keeps the expansion, the 3x3 depthwise convolution and the projection with
the residual (its fast kernels); here:

1. :func:`_temporal_branches`: per BEV row (W*C floats, per-channel weights tiled along
   it), the local (dilation 1) and cross-timestep (dilation d) temporal branches of the
   expanded features ``h`` with their LeakyReLU, and the per-channel sums of the three
   branches that Soft Feature Selection pools;
2. the branch weights from those sums (the small SFS MLP and softmax, in torch);
3. :func:`_gated`: per BEV row, the weighted branches of all T timesteps, then the gate
   (kernel-3 temporal convolution, sigmoid) times them.

Sums run in their own order and the sigmoid uses ``compiled_scan._exp_into`` (a few
float32 ulp), so the block equals the torch block to float32 rounding
(``tests/test_network_speed_paths.py`` bounds it). Training and the GPU keep the torch block.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from flowslam.sceneflow.network.backbone import LEAKY
from flowslam.sceneflow.network.compiled_scan import _exp_into

__all__ = ["temporal_branches", "gated"]

_F = np.float32
_SLOPE = _F(LEAKY[1][0])  # the blocks' LeakyReLU slope
_ONE = _F(1.0)
_EXP_LO, _EXP_HI = _F(-87.0), _F(88.0)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True, inline="always")
def _tap(out, w, row):
    """``out += w * row`` over a BEV row."""
    for q in range(out.shape[0]):
        out[q] += w[q] * row[q]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _temporal_branches(h, s, wl, bl, wc, bc, dilation, loc, cross, sums):
    """Fill ``loc`` and ``cross`` (B, T, H, L; L = W*C) from ``h`` (same shape): the temporal
    depthwise convs ``wl`` / ``wc`` (3, L: taps t - k, t, t + k; k = 1 / ``dilation``) +
    ``bl`` / ``bc``, zero padding, then LeakyReLU; ``sums`` (B, L) float64 += ``s + loc +
    cross`` summed over (T, H) (``s``: the spatial branch, same shape; each timestep's sum
    in float32, then added in float64)."""
    B, T, H, L = h.shape
    acc = np.empty(L, np.float32)
    wl0, wl1, wl2, wc0, wc1, wc2 = wl[0], wl[1], wl[2], wc[0], wc[1], wc[2]
    for b in range(B):
        for t in range(T):
            acc[:] = 0
            for y in range(H):
                lo, co, hc, so = loc[b, t, y], cross[b, t, y], h[b, t, y], s[b, t, y]
                for q in range(L):
                    lo[q] = bl[q] + wl1[q] * hc[q]
                for q in range(L):
                    co[q] = bc[q] + wc1[q] * hc[q]
                if t >= 1:
                    _tap(lo, wl0, h[b, t - 1, y])
                if t + 1 < T:
                    _tap(lo, wl2, h[b, t + 1, y])
                if t >= dilation:
                    _tap(co, wc0, h[b, t - dilation, y])
                if t + dilation < T:
                    _tap(co, wc2, h[b, t + dilation, y])
                for q in range(L):
                    v = lo[q]
                    lo[q] = max(v, v * _SLOPE)
                for q in range(L):
                    v = co[q]
                    co[q] = max(v, v * _SLOPE)
                for q in range(L):
                    acc[q] += so[q] + lo[q] + co[q]
            total = sums[b]
            for q in range(L):
                total[q] += acc[q]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _gated(s, loc, cross, weights, wg, bg, out):
    """``out`` (B, T, H, L) = ``f * sigmoid(bg + wg * f)`` where ``f = w0 s + w1 loc + w2
    cross`` (``weights`` (B, 3, L)) and ``wg`` (3, L) are the gate's taps at t - 1, t, t + 1
    (zero padding); every per-channel weight tiled along the row."""
    B, T, H, L = s.shape
    fused = np.empty((T, L), np.float32)
    e = np.empty(L, np.float32)
    bits = np.empty(L, np.int32)
    scale = bits.view(np.float32)
    for b in range(B):
        w0, w1, w2 = weights[b, 0], weights[b, 1], weights[b, 2]
        for y in range(H):
            for t in range(T):
                so, lo, co, f = s[b, t, y], loc[b, t, y], cross[b, t, y], fused[t]
                for q in range(L):
                    f[q] = so[q] * w0[q] + lo[q] * w1[q] + co[q] * w2[q]
            for t in range(T):
                z = out[b, t, y]
                for q in range(L):
                    z[q] = bg[q] + wg[1, q] * fused[t, q]
                if t >= 1:
                    _tap(z, wg[0], fused[t - 1])
                if t + 1 < T:
                    _tap(z, wg[2], fused[t + 1])
                for q in range(L):
                    z[q] = min(max(-z[q], _EXP_LO), _EXP_HI)
                _exp_into(z, e, bits, scale)
                for q in range(L):
                    z[q] = fused[t, q] / (_ONE + e[q])


def _rows(x: Tensor) -> np.ndarray:
    """(B, T, H, W, C) float32 tensor -> its (B, T, H, W*C) array (no copy when contiguous)."""
    B, T, H, W, C = x.shape
    return np.ascontiguousarray(x.numpy()).reshape(B, T, H, W * C)


def _tiled(w: Tensor, width: int) -> np.ndarray:
    """Per-channel weights (..., C) repeated for the ``width`` cells of a row: (..., width*C)."""
    a = w.detach().numpy().astype(np.float32)
    return np.ascontiguousarray(np.tile(a, (1,) * (a.ndim - 1) + (width,)))


def _tiled_parameter(module, name: str, width: int) -> np.ndarray:
    """:func:`_tiled` of the ``module``'s parameter ``name``, kept on the module (a frozen
    model tiles each weight once per row width) until that parameter changes (its storage
    or its version counter)."""
    w = getattr(module, name)
    cache = module.__dict__.setdefault("_tiled_cache", {})
    stamp = (w.data_ptr(), w._version)
    kept = cache.get((name, width))
    if kept is None or kept[0] != stamp:
        kept = cache[(name, width)] = (stamp, _tiled(w, width))
    return kept[1]


def temporal_branches(block, h: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(local branch, cross branch, SFS descriptor (B, mid): the mean of the three branches'
    sum over (T, H, W)) of the folded separable ``block`` from its expanded features ``h``
    and spatial branch ``s`` (B, T, H, W, mid)."""
    B, T, H, W, C = h.shape
    rows = _rows(h)
    loc, cross = np.empty_like(rows), np.empty_like(rows)
    sums = np.zeros((B, W * C))
    lt, ct = block.local_t, block.cross_t
    _temporal_branches(rows, _rows(s), _tiled_parameter(lt, "weight", W), _tiled_parameter(lt, "bias", W),
                       _tiled_parameter(ct, "weight", W), _tiled_parameter(ct, "bias", W), ct.dilation, loc, cross,
                       sums)
    desc = torch.from_numpy((sums.reshape(B, W, C).sum(1) / (T * H * W)).astype(np.float32))
    return torch.from_numpy(loc).view(h.shape), torch.from_numpy(cross).view(h.shape), desc


def gated(block, s: Tensor, loc: Tensor, cross: Tensor, weights: Tensor) -> Tensor:
    """The folded separable ``block``'s fused branches times their temporal gate, (B, T, H, W,
    mid), from the three branches and the SFS weights (B, 3, mid)."""
    B, T, H, W, C = s.shape
    out = np.empty((B, T, H, W * C), np.float32)
    _gated(_rows(s), _rows(loc), _rows(cross), _tiled(weights, W), _tiled_parameter(block.gate, "weight", W),
           _tiled_parameter(block.gate, "bias", W), out)
    return torch.from_numpy(out).view(s.shape)
