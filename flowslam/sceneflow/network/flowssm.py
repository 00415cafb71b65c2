"""FlowSSM decoder: voxel-to-point features, Z-order serialisation, selective scan, flow heads.

Per point of the source frame (metres, newest sensor frame):

1. *voxel-to-point*: the backbone's BEV features are sampled at the point (bilinear
   in the U-Net grid, exact cell in the pillar grid) and concatenated with the
   point's own PointNet feature -> ``d_model`` by a linear layer;
2. *point-offset features*: where the point sits inside its cells (offsets to the
   fine and coarse cell centres and to its pillar's point mean, divided by the cell
   size; height) -> ``d_offset`` by a small MLP;
3. *serialisation*: points are sorted along a 3D Z-order (Morton) curve of their
   fine voxel coordinates, per sample, into padded (B, L, .) sequences;
4. ``FlowSSMLayer`` x ``layers``: a Mamba block whose selective-scan step size Delta
   and projections B, C are computed from the *offset* features (not from the voxel
   features it scans): the offsets steer how the shared voxel features are spread
   back onto the points (MambaFlow's learned devoxelisation). Optionally a second scan
   runs over the reversed sequence (``bidirectional``);
5. un-serialisation and an MLP head: per-point residual flow (3, metres) and a
   dynamic logit.

``SceneFlowNet._source_inputs`` (model.py) gathers the inputs of steps 1-2 and the
Z-order codes; ``FlowSSMDecoder`` embeds them and runs steps 3-5.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flowslam.sceneflow.network.selective_scan import selective_scan

__all__ = [
    "morton_code",
    "spread_bits",
    "serialize",
    "bilinear_gather",
    "FlowSSMLayer",
    "FlowSSMDecoder",
]

MORTON_BITS = 21
"""Bits per axis of ``morton_code`` (3 x 21 = 63 bits of an int64)."""


def spread_bits(v: Tensor) -> Tensor:
    """Insert two zero bits between the low 21 bits of int64 ``v`` (bit i -> bit 3i)."""
    v = v.long() & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def morton_code(ix: Tensor, iy: Tensor, iz: Tensor) -> Tensor:
    """Z-order code of non-negative integer voxel coordinates (< 2**21 each): x bit i -> bit 3i,
    y -> 3i+1, z -> 3i+2."""
    return spread_bits(ix) | (spread_bits(iy) << 1) | (spread_bits(iz) << 2)


def serialize(batch: Tensor, code: Tensor, batch_size: int) -> tuple[Tensor, Tensor, Tensor]:
    """Order points by (sample, Morton code) and place them in padded per-sample sequences.

    Returns ``order`` (P,) (point indices in sequence order), ``slot`` (P,) (flat index
    ``b * L + position`` of each ordered point in a (B, L) layout) and ``lengths`` (B,).
    """
    order = torch.argsort(code, stable=True)
    order = order[torch.argsort(batch[order], stable=True)]
    lengths = torch.bincount(batch, minlength=batch_size)
    L = int(lengths.max()) if len(batch) else 0
    starts = torch.cumsum(lengths, 0) - lengths
    b_sorted = batch[order]
    pos = torch.arange(len(order), device=batch.device) - starts[b_sorted]
    return order, b_sorted * L + pos, lengths


def bilinear_gather(grid: Tensor, b: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinearly sample (B, H, W, C) at continuous cell coordinates (cell i's centre at i).

    ``u`` indexes W (x), ``v`` indexes H (y); samples outside are clamped to the border.
    Returns (P, C).
    """
    B, H, W, C = grid.shape
    flat = grid.reshape(B * H * W, C)
    u = u.clamp(0, W - 1)
    v = v.clamp(0, H - 1)
    u0 = u.floor().clamp(max=W - 2 if W > 1 else 0)
    v0 = v.floor().clamp(max=H - 2 if H > 1 else 0)
    wu = (u - u0).unsqueeze(1).to(grid.dtype)
    wv = (v - v0).unsqueeze(1).to(grid.dtype)
    u0, v0 = u0.long(), v0.long()
    u1, v1 = (u0 + 1).clamp(max=W - 1), (v0 + 1).clamp(max=H - 1)
    base = b * H
    f00 = flat[(base + v0) * W + u0]
    f01 = flat[(base + v0) * W + u1]
    f10 = flat[(base + v1) * W + u0]
    f11 = flat[(base + v1) * W + u1]
    top = torch.lerp(f00, f01, wu)
    bottom = torch.lerp(f10, f11, wu)
    return torch.lerp(top, bottom, wv)


class FlowSSMLayer(nn.Module):
    """One Mamba block over a serialised point sequence, its scan steered by offset features.

    ``h``: (B, L, d_model) voxel-derived features; ``o``: (B, L, d_offset) offset features;
    ``mask``: (B, L, 1) 1 for real points, 0 for padding (padding sits at the end).
    """

    def __init__(
        self,
        d_model: int,
        d_inner: int,
        d_state: int,
        d_offset: int,
        chunk: int = 128,
        bidirectional: bool = True,
        conv_kernel: int = 4,
    ):
        super().__init__()
        self.d_inner, self.d_state, self.chunk = d_inner, d_state, chunk
        self.directions = 2 if bidirectional else 1
        self.norm = nn.LayerNorm(d_model)
        self.in_proj = nn.Linear(d_model, 2 * d_inner)
        self.conv = (
            nn.Conv1d(d_inner, d_inner, conv_kernel, groups=d_inner, padding=conv_kernel - 1)
            if conv_kernel > 1
            else None
        )
        self.dt_proj = nn.Linear(d_offset, self.directions * d_inner)
        self.bc_proj = nn.Linear(d_offset, self.directions * 2 * d_state)
        # Mamba's S4D-real init: A = -(1..S) per channel; step sizes log-uniform in [1e-3, 1e-1]
        a = torch.arange(1, d_state + 1, dtype=torch.float32).log().repeat(self.directions, d_inner, 1)
        self.A_log = nn.Parameter(a)
        self.D = nn.Parameter(torch.ones(self.directions, d_inner))
        dt = torch.exp(torch.rand(self.directions * d_inner) * (math.log(0.1) - math.log(1e-3)) + math.log(1e-3))
        with torch.no_grad():
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))  # inverse softplus
            self.dt_proj.weight.mul_(0.1)
        self.out_proj = nn.Linear(d_inner, d_model)

    def forward(self, h: Tensor, o: Tensor, mask: Tensor) -> Tensor:
        L = h.shape[1]
        x, z = self.in_proj(self.norm(h)).chunk(2, -1)
        if self.conv is not None:  # causal depthwise conv along the sequence
            x = self.conv(x.transpose(1, 2))[..., :L].transpose(1, 2)
        x = F.silu(x) * mask  # zero padding: a scan through it from a zero state stays zero
        delta = F.softplus(self.dt_proj(o)).chunk(self.directions, -1)
        bc = self.bc_proj(o).chunk(2 * self.directions, -1)
        A = -torch.exp(self.A_log)
        y = selective_scan(x, delta[0], A[0], bc[0], bc[1], self.D[0], self.chunk)
        if self.directions == 2:  # reversed sequence: the padding comes first and stays zero
            y_rev = selective_scan(
                x.flip(1), delta[1].flip(1), A[1], bc[2].flip(1), bc[3].flip(1), self.D[1], self.chunk
            )
            y = y + y_rev.flip(1)
        return h + self.out_proj(y * F.silu(z))


class FlowSSMDecoder(nn.Module):
    """Serialise, run ``layers`` FlowSSM layers, un-serialise, predict flow (3) + dynamic logit.

    Args:
        point_in: channels of the per-point voxel-to-point input.
        offset_in: channels of the raw per-point offset input.
    """

    def __init__(
        self,
        point_in: int,
        offset_in: int,
        d_model: int = 32,
        d_inner: int = 32,
        d_state: int = 8,
        d_offset: int = 16,
        layers: int = 1,
        chunk: int = 128,
        bidirectional: bool = True,
        conv_kernel: int = 4,
        head_hidden: int = 32,
    ):
        super().__init__()
        self.embed = nn.Sequential(nn.Linear(point_in, d_model), nn.LayerNorm(d_model), nn.GELU())
        self.offset_mlp = nn.Sequential(nn.Linear(offset_in, d_offset), nn.GELU(), nn.Linear(d_offset, d_offset))
        self.layers = nn.ModuleList(
            FlowSSMLayer(d_model, d_inner, d_state, d_offset, chunk, bidirectional, conv_kernel) for _ in range(layers)
        )
        self.head = nn.Sequential(
            nn.LayerNorm(d_model), nn.Linear(d_model, head_hidden), nn.GELU(), nn.Linear(head_hidden, 4)
        )
        with torch.no_grad():  # start at zero residual flow and an undecided dynamic logit
            self.head[-1].weight.zero_()
            self.head[-1].bias.zero_()

    def forward(self, point_in: Tensor, offset_in: Tensor, batch: Tensor, code: Tensor, batch_size: int) -> Tensor:
        """(P, point_in), (P, offset_in), sample (P,), Morton code (P,) -> (P, 4) [flow xyz, logit]."""
        P = point_in.shape[0]
        if P == 0:  # nothing to scan; keep the graph connected for training
            return self.head(self.embed(point_in))
        order, slot, lengths = serialize(batch, code, batch_size)
        L = int(lengths.max())
        h_pts = self.embed(point_in)
        o_pts = self.offset_mlp(offset_in)
        h = h_pts.new_zeros(batch_size * L, h_pts.shape[1]).index_copy_(0, slot, h_pts[order])
        o = o_pts.new_zeros(batch_size * L, o_pts.shape[1]).index_copy_(0, slot, o_pts[order])
        mask = h_pts.new_zeros(batch_size * L, 1).index_fill_(0, slot, 1.0)
        h, o, mask = h.view(batch_size, L, -1), o.view(batch_size, L, -1), mask.view(batch_size, L, 1)
        for layer in self.layers:
            h = layer(h, o, mask)
        out_sorted = self.head(h.reshape(batch_size * L, -1)[slot])  # (P, 4) in sequence order
        return out_sorted.new_empty(P, 4).index_copy_(0, order, out_sorted)
