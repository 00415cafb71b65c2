"""Interpolate a timed pose stream (e.g. 200 Hz ego poses, an odometry topic) at scan times.

Translation is interpolated linearly and rotation by slerp (constant angular rate
between the two bracketing samples). Stamps may be integer nanoseconds or float
seconds, as long as source and query use the same unit; integer stamps keep exact
matches exact. Queries outside ``[stamps[0], stamps[-1]]`` are not extrapolated:
they are marked invalid and their pose is all-NaN.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger(__name__)


def sorted_unique_poses(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort a pose stream by time and drop repeated stamps (keeping the first)."""
    stamps = np.asarray(stamps)
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], np.asarray(poses, dtype=np.float64)[order]
    keep = np.ones(len(stamps), dtype=bool)
    keep[1:] = stamps[1:] != stamps[:-1]
    return stamps[keep], poses[keep]


def interpolate_poses(
    stamps: np.ndarray, poses: np.ndarray, query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``T_world_x`` (M,4,4) at ``query`` times, and a (M,) bool mask of covered queries.

    ``stamps`` (K,) must be strictly increasing (see ``sorted_unique_poses``) and
    ``poses`` (K,4,4) rigid transforms. Uncovered queries get NaN poses.
    """
    stamps = np.asarray(stamps)
    poses = np.asarray(poses, dtype=np.float64)
    query = np.asarray(query)
    out = np.full((len(query), 4, 4), np.nan)
    if len(stamps) == 0:
        return out, np.zeros(len(query), dtype=bool)
    valid = (query >= stamps[0]) & (query <= stamps[-1])
    idx = np.searchsorted(stamps, query, side="right") - 1
    exact = valid & (stamps[np.clip(idx, 0, len(stamps) - 1)] == query)
    out[exact] = poses[idx[exact]]
    interp = valid & ~exact
    if interp.any():
        i0 = idx[interp]
        i1 = i0 + 1
        # differences first, so integer nanosecond stamps lose no precision
        alpha = (query[interp] - stamps[i0]).astype(np.float64) / (stamps[i1] - stamps[i0]).astype(np.float64)
        r0 = Rotation.from_matrix(poses[i0, :3, :3])
        r1 = Rotation.from_matrix(poses[i1, :3, :3])
        delta = (r0.inv() * r1).as_rotvec()
        rot = r0 * Rotation.from_rotvec(alpha[:, None] * delta)
        res = np.zeros((len(i0), 4, 4))
        res[:, :3, :3] = rot.as_matrix()
        res[:, :3, 3] = poses[i0, :3, 3] + alpha[:, None] * (poses[i1, :3, 3] - poses[i0, :3, 3])
        res[:, 3, 3] = 1.0
        out[interp] = res
    return out, valid


@dataclass
class ScanPoses:
    """GT poses of a reader's scans from a timed pose stream.

    ``partial`` (N,4,4) holds NaN for uncovered scans and ``valid`` (N,) marks covered
    ones; ``full`` is ``partial`` when every scan is covered, else None (the value a
    reader puts in ``Dataset.gt_poses``).
    """

    partial: np.ndarray
    valid: np.ndarray

    @property
    def full(self) -> np.ndarray | None:
        return self.partial if self.valid.all() else None

    def at(self, index: int) -> np.ndarray | None:
        """The pose of scan ``index``, or None when the stream does not cover it."""
        return self.partial[index] if self.valid[index] else None


def poses_at_scans(stamps: np.ndarray, poses: np.ndarray, scan_stamps: np.ndarray, where: str) -> ScanPoses:
    """Sort/dedupe a pose stream, interpolate it at the scan stamps, and log partial coverage."""
    src_t, src_p = sorted_unique_poses(stamps, poses)
    partial, valid = interpolate_poses(src_t, src_p, scan_stamps)
    if not valid.all():
        log.warning("%s: GT poses cover only %d of %d scans; the others get no GT pose",
                    where, int(valid.sum()), len(valid))
    return ScanPoses(partial, valid)
