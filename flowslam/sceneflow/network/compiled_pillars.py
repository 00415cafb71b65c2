"""The pillar PointNet, its max-pooling and the stride-2 stem on the occupied pillars only
(CPU float32 inference).

Same arithmetic as :class:`flowslam.sceneflow.network.voxelize.PillarEncoder` (``amax``
pooling, BatchNorm folded) followed by the model's stem (a 2x2 stride-2 convolution with
its folded BatchNorm and LeakyReLU, :class:`flowslam.sceneflow.network.backbone._Down`).
The torch form scatters the pooled features into the dense (B, T, 256, 256, C) pillar grid
(21 MB for the shipped model, ~8 % of it occupied on a 64-beam scan) and convolves all of
it; here the occupied pillars are numbered in the order their first point comes
(:func:`_occupied`), the PointNet runs on the points (:func:`_point_inputs`, then one
oneDNN layer with its ReLU) and is max-pooled per pillar (:func:`_max_pool`), and each
pillar adds its 2x2 tap to the one stem cell it feeds (:func:`_stem`), which starts from
the bias that an empty input gives.

The model also reads the pooled feature of a point's own pillar at two timesteps: the
result carries a table of the pooled rows with a zero row last, and the row of every grid
cell (-1, that zero row, where the cell is empty).

Sums run in their own order, so the stem output and the point features equal the torch
form's to float32 rounding (``tests/test_network_speed_paths.py`` bounds it). Training,
``mean`` pooling, a stem of stride 1 and the GPU keep the torch form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import njit
from torch import Tensor

from flowslam.sceneflow.network.backbone import LEAKY, RELU, linear

__all__ = ["CompiledPillars", "pillars_and_stem"]

_F = np.float32


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _occupied(points, cell, num_cells):
    """Number the occupied cells in the order of their first point: (the row of each point
    (P,); the row of each cell, -1 where empty (num_cells,); the cell of each row (S,); the
    x, y, z sums and the point count of each row (S, 4))."""
    P = points.shape[0]
    row_of = np.full(num_cells, -1, np.int64)
    slot = np.empty(P, np.int64)
    sums = np.zeros((P, 4), np.float32)
    cells = np.empty(P, np.int64)
    S = 0
    for p in range(P):
        r = row_of[cell[p]]
        if r < 0:
            r = S
            row_of[cell[p]] = r
            cells[r] = cell[p]
            S += 1
        slot[p] = r
        sums[r, 0] += points[p, 0]
        sums[r, 1] += points[p, 1]
        sums[r, 2] += points[p, 2]
        sums[r, 3] += _F(1.0)
    return slot, row_of, cells[:S], sums[:S]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _point_inputs(points, slot, sums, ix, iy, time, half_extent, extent, voxel, z_mid, z_half, t_scale, raw):
    """``raw`` (P, 9): ``PillarEncoder.point_inputs`` (position over the half extent, height,
    offsets to the cell centre and to the cell's point mean in voxels, time)."""
    for p in range(points.shape[0]):
        r = slot[p]
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        n = sums[r, 3]
        raw[p, 0] = px / half_extent
        raw[p, 1] = py / half_extent
        raw[p, 2] = (pz - z_mid) / z_half
        raw[p, 3] = (px - ((_F(ix[p]) + _F(0.5)) * voxel - extent)) / voxel
        raw[p, 4] = (py - ((_F(iy[p]) + _F(0.5)) * voxel - extent)) / voxel
        raw[p, 5] = (px - sums[r, 0] / n) / voxel
        raw[p, 6] = (py - sums[r, 1] / n) / voxel
        raw[p, 7] = (pz - sums[r, 2] / n) / voxel
        raw[p, 8] = _F(time[p]) / t_scale


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _max_pool(feats, slot, rows):
    """(rows + 1, C): the largest of ``feats`` (P, C, >= 0) per row, a zero row last."""
    C = feats.shape[1]
    pooled = np.zeros((rows + 1, C), np.float32)
    for p in range(feats.shape[0]):
        best, f = pooled[slot[p]], feats[p]
        for k in range(C):
            best[k] = max(best[k], f[k])
    return pooled


@njit(cache=True, nogil=True, error_model="numpy", fastmath=True)
def _stem(pooled, cells, size, weight, bias, slope, out):
    """``out`` (B*T, size/2, size/2, Co): the 2x2 stride-2 convolution ``weight`` (2, 2, C,
    Co) + ``bias`` of the pillar grid whose occupied cells ``cells`` hold ``pooled`` (rows
    in the same order), then LeakyReLU with ``slope``."""
    BT, h, w, Co = out.shape
    C = pooled.shape[1]
    for b in range(BT):
        for y in range(h):
            for x in range(w):
                o = out[b, y, x]
                for k in range(Co):
                    o[k] = bias[k]
    for r in range(cells.shape[0]):
        c = cells[r]
        ix = c % size
        iy = (c // size) % size
        bt = c // (size * size)
        o = out[bt, iy // 2, ix // 2]
        taps = weight[iy % 2, ix % 2]
        f = pooled[r]
        for i in range(C):
            fi = f[i]
            row = taps[i]
            for k in range(Co):
                o[k] += fi * row[k]
    for b in range(BT):
        for y in range(h):
            for x in range(w):
                o = out[b, y, x]
                for k in range(Co):
                    v = o[k]
                    o[k] = max(v, v * slope)


@dataclass
class CompiledPillars:
    """What the model needs from the pillar stage: the stem output (B, T, H/2, W/2, Co), the
    per-point PointNet features (P, C) and inputs (P, 9), and the pooled feature of any
    grid cell as ``table[row_of[cell]]`` (the last row of ``table`` is zeros, for empty cells)."""

    stem: Tensor
    point_feats: Tensor
    raw: Tensor
    table: Tensor
    row_of: Tensor


def pillars_and_stem(encoder, stem, index) -> CompiledPillars:
    """The folded ``encoder`` (``PillarEncoder``, ``amax`` pooling) and the folded stride-2
    ``stem`` (``_Down``) on the points of ``index`` (a ``PillarIndex``)."""
    g = encoder.grid
    B, T, n = index.batch_size, index.num_frames, g.size
    points = np.ascontiguousarray(index.points.to(torch.float32).numpy())
    slot, row_of, cells, sums = _occupied(points, index.cell.numpy(), B * T * n * n)
    raw = np.empty((len(points), 9), np.float32)
    z_mid, z_half = 0.5 * (g.z_max + g.z_min), 0.5 * (g.z_max - g.z_min)
    _point_inputs(points, slot, sums, index.ix.numpy(), index.iy.numpy(), index.time.numpy(), _F(g.half_extent),
                  _F(g.extent), _F(g.voxel_size), _F(z_mid), _F(z_half), _F(max(T - 1, 1)), raw)
    raw_t = torch.from_numpy(raw)
    feats = linear(raw_t, encoder.linear, RELU)  # the PointNet layer and its ReLU (oneDNN)
    pooled = _max_pool(feats.numpy(), slot, len(cells))
    conv = stem.conv
    Co = conv.out_channels
    out = np.empty((B * T, n // 2, n // 2, Co), np.float32)
    # (Co, C, 2, 2) -> (2, 2, C, Co): per tap, one (C, Co) matrix
    w = np.ascontiguousarray(conv.weight.detach().numpy().transpose(2, 3, 1, 0))
    _stem(pooled, cells, n, w, conv.bias.detach().numpy().astype(np.float32), _F(LEAKY[1][0]), out)
    return CompiledPillars(torch.from_numpy(out).view(B, T, n // 2, n // 2, Co), feats, raw_t,
                           torch.from_numpy(pooled), torch.from_numpy(row_of))
