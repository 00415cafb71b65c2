"""The decoder's per-point inputs gathered in one compiled pass (CPU float32 inference).

:meth:`flowslam.sceneflow.network.model.SceneFlowNet._source_inputs` reads, for each
in-grid point of the source frame, the U-Net output at frames t and t+1 (bilinearly, at
the point's position), the pooled feature of its own pillar at t and t+1, its PointNet
feature, and its offsets. In torch that is two bilinear gathers of four corner rows and
three ``lerp`` each, two table lookups, a gather and two concatenations: ~7.7 ms per
KITTI pair for 16k points, mostly in temporaries. Here one loop writes each point's
two rows.

Same arithmetic as the torch form: the cell coordinates ``u``, ``v`` and the Z-order code
stay in torch; the corner weights and the clamps are float32; each ``lerp`` is torch's
(``start + w (end - start)`` for ``|w| < 0.5``, else ``end + (w - 1)(end - start)``, one
rounding per multiply-add, here through float64). ``tests/test_network_speed_paths.py``
compares both forms. Used where the compiled pillar stage runs
(:mod:`~flowslam.sceneflow.network.compiled_pillars`), whose ``row_of`` it reads.

Units: the model's (metres in the points, cells in ``u``, ``v``).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

__all__ = ["decoder_inputs"]

_F = np.float32


@njit(cache=True, nogil=True, inline="always")
def _lerp(start, end, w):
    """torch's ``lerp`` of two float32 values with a float32 weight (one rounding, as a
    fused multiply-add: the product is exact in float64)."""
    d = np.float64(end) - np.float64(start)
    if abs(w) < 0.5:
        return _F(np.float64(start) + np.float64(w) * np.float64(_F(d)))
    return _F(np.float64(end) + np.float64(w - _F(1.0)) * np.float64(_F(d)))


@njit(cache=True, nogil=True)
def _bilinear_into(unet, bt, u, v, out, col):
    """``out[col:col+C]`` = the (BT, H, W, C) ``unet`` at image ``bt`` sampled bilinearly at
    (``u`` along W, ``v`` along H), clamped to the border (``flowssm.bilinear_gather``)."""
    H, W, C = unet.shape[1], unet.shape[2], unet.shape[3]
    u = min(max(u, _F(0.0)), _F(W - 1))
    v = min(max(v, _F(0.0)), _F(H - 1))
    u0 = min(np.floor(u), _F(W - 2 if W > 1 else 0))
    v0 = min(np.floor(v), _F(H - 2 if H > 1 else 0))
    wu, wv = u - u0, v - v0
    i0, j0 = int(u0), int(v0)
    i1, j1 = min(i0 + 1, W - 1), min(j0 + 1, H - 1)
    f00, f01, f10, f11 = unet[bt, j0, i0], unet[bt, j0, i1], unet[bt, j1, i0], unet[bt, j1, i1]
    for k in range(C):
        out[col + k] = _lerp(_lerp(f00[k], f01[k], wu), _lerp(f10[k], f11[k], wu), wv)


@njit(cache=True, nogil=True)
def _gather(unet, T, src, n, b, ix, iy, u, v, table, row_of, point_feats, sel, raw, point_in, offset_in):
    """Fills ``point_in`` (P, 2 C + 3 Cp) and ``offset_in`` (P, 8) of the P source points
    (module doc; their sample ``b``, cell ``ix``, ``iy``, U-Net coordinates ``u``, ``v``,
    row ``sel`` among the in-grid points)."""
    C, Cp = unet.shape[3], table.shape[1]
    zero = table.shape[0] - 1  # the table's zero row (an empty cell's -1)
    for p in range(sel.shape[0]):
        row = point_in[p]
        _bilinear_into(unet, b[p] * T + src, u[p], v[p], row, 0)
        _bilinear_into(unet, b[p] * T + src + 1, u[p], v[p], row, C)
        for t in range(2):
            r = row_of[((b[p] * T + src + t) * n + iy[p]) * n + ix[p]]
            pooled = table[zero if r < 0 else r]
            for k in range(Cp):
                row[2 * C + t * Cp + k] = pooled[k]
        feat = point_feats[sel[p]]
        for k in range(Cp):
            row[2 * C + 2 * Cp + k] = feat[k]
        q, o = raw[sel[p]], offset_in[p]
        o[0], o[1] = q[3], q[4]  # pillar-centre offsets
        o[2], o[3] = u[p] - np.rint(u[p]), v[p] - np.rint(v[p])  # U-Net-cell offsets
        o[4], o[5], o[6] = q[5], q[6], q[7]  # pillar-mean offsets
        o[7] = q[2]  # height


def decoder_inputs(unet: Tensor, src: int, n: int, b: Tensor, ix: Tensor, iy: Tensor, u: Tensor, v: Tensor,
                   table: Tensor, row_of: Tensor, point_feats: Tensor, sel: Tensor,
                   raw: Tensor) -> tuple[Tensor, Tensor]:
    """(voxel-to-point inputs (P, 2 C + 3 Cp), offset inputs (P, 8)) of the source points
    ``sel`` (rows of the in-grid points; ``b``, ``ix``, ``iy``, ``u``, ``v``: theirs) from the
    U-Net output ``unet`` (B, T, h, w, C), the pooled pillar ``table`` with ``row_of`` (grid
    of ``n`` x ``n`` cells per frame), the PointNet features and the raw point inputs."""
    B, T = unet.shape[0], unet.shape[1]
    C, Cp = unet.shape[4], table.shape[1]
    P = len(sel)
    point_in = np.empty((P, 2 * C + 3 * Cp), np.float32)
    offset_in = np.empty((P, 8), np.float32)
    grid = np.ascontiguousarray(unet.numpy()).reshape(B * T, unet.shape[2], unet.shape[3], C)
    _gather(grid, T, src, n, b.numpy(), ix.numpy(), iy.numpy(), u.numpy(), v.numpy(), table.numpy(),
            row_of.numpy(), point_feats.numpy(), sel.numpy(), raw.numpy(), point_in, offset_in)
    return torch.from_numpy(point_in), torch.from_numpy(offset_in)
