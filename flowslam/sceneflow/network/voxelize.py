"""Pillar (BEV cell) indexing of multi-frame point clouds and PointNet pooling into a BEV+time grid.

Frames and units
----------------
All points are in metres, in the sensor frame of the *newest* scan (the caller has
already compensated the older scans with its own ego-motion estimate). The grid is
a square of ``2 * half_extent`` metres centred on that sensor (``2 * crop`` with an
inference crop, ``BEVGrid``), cells of ``voxel_size`` metres, ``z`` kept in
``[z_min, z_max)``. Row ``iy`` indexes y, column ``ix`` indexes x::

    ix = floor((x + extent) / voxel_size),   iy = floor((y + extent) / voxel_size)

Layout of the dense grid: **(B, T, H, W, C)**, contiguous, channels last: time is an
axis of its own (oldest frame at t = 0, newest at t = T-1) and every (b, t, iy, ix)
cell holds a C-vector. It is the (B, C, T, H, W) tensor of the spec stored
channels-last, which is what makes the per-timestep 2D convolutions fast on CPU.
Empty cells are zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = ["BEVGrid", "PillarIndex", "index_points", "PillarEncoder", "POINT_FEATURES"]

POINT_FEATURES = 9
"""Raw per-point inputs of the PointNet: x, y, z (normalised), offset to the cell centre (2),
offset to the mean of the cell's points (3), time index (normalised)."""


@dataclass(frozen=True)
class BEVGrid:
    """A square bird's-eye-view grid around the newest sensor (metres).

    ``half_extent`` is the grid the network was trained on: it also scales the points'
    position inputs (``PillarEncoder.point_inputs``) and places the decoder's Z-order
    origin at its corner. ``crop`` (inference only, None: none) makes the grid cover only
    ``[-crop, crop)`` -- its cells the same as the full grid's there, the inputs scaled as
    before -- so that the convolutions run on the square around the sensor alone; points
    beyond are outside (``inside`` False)."""

    half_extent: float = 51.2
    voxel_size: float = 0.4
    z_min: float = -3.0
    z_max: float = 5.0
    crop: float | None = None

    @property
    def extent(self) -> float:
        """Half-width (m) of the square the cells cover: ``crop``, or ``half_extent``."""
        return self.half_extent if self.crop is None else self.crop

    @property
    def size(self) -> int:
        """Cells per side (H = W)."""
        return int(round(2 * self.extent / self.voxel_size))

    def cells(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(ix, iy, inside)`` of (N,3) points; ``inside`` also requires z in [z_min, z_max)."""
        n = self.size
        q = torch.floor((points[:, :2] + self.extent) / self.voxel_size).long()
        ix, iy = q[:, 0], q[:, 1]
        z = points[:, 2]
        inside = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n) & (z >= self.z_min) & (z < self.z_max)
        return ix.clamp(0, n - 1), iy.clamp(0, n - 1), inside

    def centres(self, ix: Tensor, iy: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
        """(N,2) x, y of cell centres (m)."""
        c = torch.stack([ix, iy], 1).to(dtype) + 0.5
        return c * self.voxel_size - self.extent


@dataclass
class PillarIndex:
    """The in-grid points of a batch of multi-frame samples, flattened, with their cells.

    ``P`` is the number of in-grid points over all samples and frames.
    """

    points: Tensor
    """(P,3) float, metres, newest sensor frame."""
    batch: Tensor
    """(P,) long, sample of each point."""
    time: Tensor
    """(P,) long, frame of each point (0 = oldest, T-1 = newest)."""
    ix: Tensor
    """(P,) long, grid column."""
    iy: Tensor
    """(P,) long, grid row."""
    cell: Tensor
    """(P,) long, flat index into the (B, T, H, W) grid."""
    frame_index: Tensor
    """(P,) long, index of the point inside its own input frame."""
    batch_size: int
    num_frames: int
    grid: BEVGrid


def index_points(frames: list[list[Tensor]], grid: BEVGrid) -> tuple[PillarIndex, list[list[Tensor]]]:
    """Flatten a batch of multi-frame samples and index every in-grid point into the grid.

    Args:
        frames: ``frames[b][t]`` is an (N_bt, 3) tensor, oldest frame first; every sample
            has the same number of frames T, point counts differ freely.
        grid: the BEV grid.

    Returns:
        The ``PillarIndex`` of the in-grid points, and ``inside[b][t]``, the (N_bt,) bool
        masks of the points that fell in the grid.
    """
    B, T = len(frames), len(frames[0])
    if any(len(f) != T for f in frames):
        raise ValueError("every sample must have the same number of frames")
    n = grid.size
    pts, bs, ts, ixs, iys, idx, masks = [], [], [], [], [], [], []
    for b, sample in enumerate(frames):
        row = []
        for t, p in enumerate(sample):
            if p.dim() != 2 or p.shape[1] != 3:
                raise ValueError(f"frame ({b}, {t}) has shape {tuple(p.shape)}, expected (N, 3)")
            ix, iy, inside = grid.cells(p)
            row.append(inside)
            keep = torch.nonzero(inside).squeeze(1)
            pts.append(p[keep])
            ixs.append(ix[keep])
            iys.append(iy[keep])
            idx.append(keep)
            bs.append(torch.full_like(keep, b))
            ts.append(torch.full_like(keep, t))
        masks.append(row)
    batch, time, ix, iy = torch.cat(bs), torch.cat(ts), torch.cat(ixs), torch.cat(iys)
    cell = ((batch * T + time) * n + iy) * n + ix
    index = PillarIndex(torch.cat(pts), batch, time, ix, iy, cell, torch.cat(idx), B, T, grid)
    return index, masks


def _scatter_mean_at(values: Tensor, cell: Tensor, num_cells: int) -> Tensor:
    """(P, F): for each point, the mean of ``values`` (P, F) over the points of its cell."""
    F = values.shape[1]
    total = values.new_zeros(num_cells, F + 1)
    total.index_add_(0, cell, torch.cat([values, values.new_ones(len(cell), 1)], 1))
    at = total[cell]
    return at[:, :F] / at[:, F:]


class PillarEncoder(nn.Module):
    """PointNet over the points of each cell and frame, max-pooled into the (B, T, H, W, C) grid.

    Per point: a linear layer + BatchNorm + ReLU on ``POINT_FEATURES`` inputs (position,
    offsets to the cell centre and to the cell's point mean, all divided by the voxel
    size, and the time index). Pooling is ``torch.scatter_reduce`` ("amax" or "mean")
    straight into the dense grid.
    """

    def __init__(self, grid: BEVGrid, channels: int, pooling: str = "amax"):
        super().__init__()
        if pooling not in ("amax", "mean"):
            raise ValueError(f"pooling must be 'amax' or 'mean', got {pooling!r}")
        self.grid = grid
        self.channels = channels
        self.pooling = pooling
        self.linear = nn.Linear(POINT_FEATURES, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)
        self.folded = False

    @torch.no_grad()
    def fold_batchnorm(self) -> None:
        """Fold the BatchNorm into the linear layer (eval/inference only)."""
        if self.folded:
            return
        scale = self.norm.weight / torch.sqrt(self.norm.running_var + self.norm.eps)
        self.linear.weight.mul_(scale.unsqueeze(1))
        self.linear.bias = nn.Parameter(self.norm.bias - self.norm.running_mean * scale)
        self.folded = True

    def point_inputs(self, index: PillarIndex) -> Tensor:
        """(P, POINT_FEATURES) raw inputs of the PointNet (dimensionless)."""
        g = self.grid
        p = index.points.to(self.linear.weight.dtype)
        n_cells = index.batch_size * index.num_frames * g.size * g.size
        mean = _scatter_mean_at(p, index.cell, n_cells)
        centre = g.centres(index.ix, index.iy, p.dtype)
        z_mid, z_half = 0.5 * (g.z_max + g.z_min), 0.5 * (g.z_max - g.z_min)
        t = index.time.to(p.dtype) / max(index.num_frames - 1, 1)
        return torch.cat(
            [
                p[:, :2] / g.half_extent,
                ((p[:, 2] - z_mid) / z_half).unsqueeze(1),
                (p[:, :2] - centre) / g.voxel_size,
                (p - mean) / g.voxel_size,
                t.unsqueeze(1),
            ],
            1,
        )

    def forward(self, index: PillarIndex) -> tuple[Tensor, Tensor, Tensor]:
        """Returns the dense grid (B, T, H, W, C), the per-point features (P, C) and the raw
        per-point inputs (P, POINT_FEATURES) (columns: x, y, z, centre offset x, y, mean
        offset x, y, z, time; see ``point_inputs``)."""
        g = self.grid
        raw = self.point_inputs(index)
        feats = self.linear(raw)
        feats = torch.relu(feats if self.folded else self.norm(feats))
        n_cells = index.batch_size * index.num_frames * g.size * g.size
        C = self.channels
        dense = feats.new_zeros(n_cells, C)
        target = index.cell.unsqueeze(1).expand(-1, C)
        # in place into the fresh zero grid (no copy of the grid); features are >= 0 after
        # the ReLU, so for "amax" the zero initial value is neutral
        if self.pooling == "amax":
            dense.scatter_reduce_(0, target, feats, reduce="amax", include_self=True)
        else:
            dense.scatter_reduce_(0, target, feats, reduce="mean", include_self=False)
        return dense.view(index.batch_size, index.num_frames, g.size, g.size, C), feats, raw
