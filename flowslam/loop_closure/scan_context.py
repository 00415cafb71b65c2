"""Scan Context descriptor (Kim & Kim, IROS 2018): a polar grid of maximum heights.

A scan (points in its sensor frame, metres) is split into ``rings`` radial bins of
equal width up to ``max_range_m`` and ``sectors`` azimuthal bins of equal angle;
each bin holds the highest ``z + height_offset_m`` of its points (0 when empty or
below ``-height_offset_m``). Sector ``k`` covers azimuths ``[k, k+1) * 2 pi / sectors``,
measured counter-clockwise from the sensor's x axis.

A yaw of the sensor shifts the columns: if ``p_a = Rz(theta) p_b`` then the
descriptor of ``a`` is the one of ``b`` rolled by ``theta / (2 pi / sectors)``
columns. :func:`distance` finds that roll and returns it as the yaw of ``T_a_b``.
The ring key (mean of each ring) does not change with yaw and indexes the KD-tree.
"""

from __future__ import annotations

import numpy as np

from flowslam.config.loop_closure import ScanContextConfig

__all__ = ["scan_context", "ring_key", "distance", "distances", "shift_to_yaw"]


def scan_context(points: np.ndarray, config: ScanContextConfig | None = None) -> np.ndarray:
    """(rings, sectors) float32 descriptor of (N,3) points in the sensor frame (m)."""
    c = config or ScanContextConfig()
    p = np.asarray(points)
    x, y = p[:, 0].astype(np.float64), p[:, 1].astype(np.float64)
    r = np.hypot(x, y)
    keep = (r > 0) & (r < c.max_range_m)
    height = p[keep, 2].astype(np.float64) + c.height_offset_m
    ring = np.minimum((r[keep] * (c.rings / c.max_range_m)).astype(np.int64), c.rings - 1)
    azimuth = np.mod(np.arctan2(y[keep], x[keep]), 2 * np.pi)
    sector = np.minimum((azimuth * (c.sectors / (2 * np.pi))).astype(np.int64), c.sectors - 1)
    desc = np.zeros(c.rings * c.sectors)
    np.maximum.at(desc, ring * c.sectors + sector, height)
    return desc.reshape(c.rings, c.sectors).astype(np.float32)


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Yaw-invariant (rings,) key: the mean of each ring (row) of a descriptor."""
    return np.asarray(desc, dtype=np.float64).mean(axis=-1)


def _unit_columns(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit norm (zero columns stay zero) and the mask of non-empty ones."""
    d = np.asarray(desc, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-2, keepdims=True)
    valid = norm > 0
    return np.where(valid, d / np.where(valid, norm, 1.0), 0.0), valid[..., 0, :]


def distances(query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column-shift distance of ``query`` (R,S) to each of ``candidates`` (M,R,S).

    For each shift ``s`` the distance is the mean cosine distance ``1 - cos`` over
    the column pairs ``(query[:, k], roll(candidate, s)[:, k])`` where both columns
    are non-empty (1 if there is none); the minimum over ``s`` is returned with its
    shift. Returns ``(distance (M,) in [0, 2], shift (M,) int in [0, S))`` where
    ``roll(candidate, shift, axis=1)`` best matches ``query``.
    """
    qa, qv = _unit_columns(query)
    cb, cv = _unit_columns(np.asarray(candidates).reshape((-1,) + np.shape(query)))
    S = qa.shape[-1]
    # cos[m, k, l]: query column k vs candidate column l; shift s pairs k with l = k - s.
    cos = np.einsum("rk,mrl->mkl", qa, cb)
    both = qv[None, :, None] & cv[:, None, :]
    k = np.arange(S)[None, :]
    l_of_s = (k - np.arange(S)[:, None]) % S  # (shift, k)
    sim = cos[:, k, l_of_s].sum(axis=-1)  # (M, shift)
    count = both[:, k, l_of_s].sum(axis=-1)
    dist = np.where(count > 0, 1.0 - sim / np.maximum(count, 1), 1.0)
    shift = np.argmin(dist, axis=1)
    return dist[np.arange(len(dist)), shift], shift


def distance(a: np.ndarray, b: np.ndarray) -> tuple[float, int]:
    """Column-shift distance of two descriptors and the roll of ``b`` that matches ``a``."""
    d, s = distances(a, np.asarray(b)[None])
    return float(d[0]), int(s[0])


def shift_to_yaw(shift: int, sectors: int) -> float:
    """Yaw (rad, in (-pi, pi]) of ``T_a_b`` for the column shift from :func:`distance`."""
    yaw = shift * 2 * np.pi / sectors
    return float(yaw - 2 * np.pi if yaw > np.pi else yaw)
