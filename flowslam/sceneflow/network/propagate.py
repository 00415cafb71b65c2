"""Sub-sampling a scan for the network and spreading its per-point outputs back to every point.

The network runs on a random subset (16k-32k points) of a 64-beam scan (~120k); every
point of the scan still needs a flow. ``propagate`` gives each unsampled point the mean
output of the sampled points in its 3D voxel, trying voxels of ``voxel_size``, then
4x larger, ... (0.25, 1, 4, 16 m by default), and the nearest sampled point for what
is still left (isolated points far away). Sampled points keep their own outputs. Metres, any frame (both point sets
in the same one); torch, device-agnostic (on CPU the binary search runs in NumPy, same result).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["random_subsample", "voxel_keys", "propagate"]

_OFFSET = 1 << 20  # keeps quantised coordinates non-negative for +-2**20 voxels


def random_subsample(num_points: int, num_samples: int, generator: torch.Generator | None = None,
                     device: torch.device | str | None = None) -> Tensor:
    """Sorted indices of ``min(num_samples, num_points)`` distinct points, uniformly at random."""
    if num_samples >= num_points:
        return torch.arange(num_points, device=device)
    idx = torch.randperm(num_points, generator=generator)[:num_samples]
    return torch.sort(idx).values.to(device)


def voxel_keys(points: Tensor, voxel_size: float) -> Tensor:
    """(N,) int64 key of the 3D voxel of each point (21 bits per axis)."""
    return _pack(torch.floor(points / voxel_size).long())


def _pack(q: Tensor) -> Tensor:
    """(N,) int64 key of (N,3) integer voxel coordinates."""
    q = (q + _OFFSET).clamp_(0, (1 << 21) - 1)
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def _search_sorted(keys: Tensor, queries: Tensor) -> Tensor:
    """``torch.searchsorted(keys, queries)`` (left side) for int64 tensors.

    On CPU NumPy's binary search is used: the same positions, ~3x faster than torch's
    (measured on 108k queries into 16k keys, torch 2.13).
    """
    if keys.device.type == "cpu":
        return torch.from_numpy(np.searchsorted(keys.numpy(), queries.numpy()))
    return torch.searchsorted(keys, queries)


def _nearest(query: Tensor, ref: Tensor, chunk: int = 4096) -> Tensor:
    """Index into ``ref`` of the nearest point of each query point (chunked brute force)."""
    out = []
    for s in range(0, len(query), chunk):
        out.append(torch.cdist(query[s : s + chunk], ref).argmin(1))
    return torch.cat(out) if out else query.new_zeros(0, dtype=torch.long)


def propagate(
    points: Tensor,
    sample_index: Tensor,
    values: Tensor,
    voxel_size: float = 0.25,
    max_levels: int = 4,
    growth_log2: int = 2,
) -> Tensor:
    """Per-point values for all of ``points`` from the values of a sampled subset.

    Args:
        points: (N,3) every point of the scan (m).
        sample_index: (n,) long indices of the sampled points into ``points``.
        values: (n, K) outputs at the sampled points (e.g. flow and dynamic logit).
        voxel_size: finest voxel edge (m); level k uses ``voxel_size * 2**(growth_log2 * k)``.
        max_levels: voxel levels tried before the nearest-neighbour fallback.
        growth_log2: log2 of the voxel size ratio between levels (2: 4x).

    Returns:
        (N, K) values.
    """
    N = len(points)
    out = values.new_zeros((N,) + values.shape[1:])
    if len(sample_index) == 0:
        return out
    flat = values.reshape(len(values), -1)
    out_flat = out.view(N, -1)
    out_flat[sample_index] = flat
    todo = torch.ones(N, dtype=torch.bool, device=points.device)
    todo[sample_index] = False
    left = torch.nonzero(todo).squeeze(1)
    # integer coordinates at the finest level; coarser levels are arithmetic shifts (floor)
    q_ref = points[sample_index].div_(voxel_size).floor_().long()  # the gathers are copies: in place
    q_left = points[left].div_(voxel_size).floor_().long()
    for level in range(max_levels):
        if len(left) == 0:
            return out
        shift = growth_log2 * level
        keys, inverse = torch.unique(_pack(q_ref >> shift), return_inverse=True)
        sums = flat.new_zeros(len(keys), flat.shape[1]).index_add_(0, inverse, flat)
        counts = flat.new_zeros(len(keys)).index_add_(0, inverse, flat.new_ones(len(inverse)))
        means = sums / counts.unsqueeze(1)  # per occupied voxel
        qk = _pack(q_left >> shift)
        pos = _search_sorted(keys, qk).clamp_(max=len(keys) - 1)
        hit = keys[pos] == qk
        found, rest = torch.nonzero(hit).squeeze(1), torch.nonzero(~hit).squeeze(1)
        out_flat.index_copy_(0, left[found], means[pos[found]])
        left, q_left = left[rest], q_left[rest]
    if len(left):
        out_flat[left] = flat[_nearest(points[left], points[sample_index])]
    return out
