"""The static map and the removed (dynamic) points, placed with the (optimised) poses.

Frames and units: points are kept per scan in that scan's *sensor frame* (m), so the
maps can be rebuilt with any trajectory (the backend's poses change after loop
closures); :meth:`StaticMapBuilder.cloud` maps them into the world with
``T_world_sensor`` and voxel-downsamples the union (voxel centroids, mean intensity).

Per-scan storage (the memory bound)
-----------------------------------
- Static points: voxel-downsampled on arrival (``voxel_size``; centroid and mean
  intensity per voxel), then, when the scan comes with its odometry pose (always
  through :meth:`StaticMapBuilder.on_output`, which chains the frontend's
  ``T_prev_curr``), only the voxels *new to the map* are kept: those whose world voxel
  (odometry frame, ``voxel_size`` grid) no earlier scan of the last ``dedup_window``
  scans (default 50) saw. A surface seen by many consecutive scans is so stored
  once, in the frame of the first scan that saw it, and the map stays re-expressible
  with any later (loop-corrected) trajectory: consecutive scans move together under a
  correction, so the scan that keeps a voxel places it where the others would have.
  Stored as int16 centimetres plus a float16 intensity (8 bytes a point), capped at
  ``max_points_per_frame`` (seeded random subset; after the first scan the new voxels
  rarely reach it). Memory then grows with the space explored, not with the frames:
  on the simulated KITTI-00 path (64 x 512 beams, 0.82 m a scan, ~16k voxels a scan)
  about 1,600 points (13 kB) a scan, instead of the 10,000 (80 kB) a scan that a
  plain per-scan cap kept. The recently seen voxels (sorted int64 keys and the last
  scan that saw each, pruned to the window) are bounded: ~250k keys, 4 MB. A scan
  given without a pose (:meth:`StaticMapBuilder.add` without ``T_world_sensor``, or
  after a frontend output without ``T_prev_curr``, which restarts the odometry chain)
  is kept whole (up to the cap), as is every scan with ``dedup_window=0``.
- Dynamic points (those the frontend marked dynamic, i.e. removed from the map): one
  point per voxel and instance (the first; coordinates and ids unaveraged), same cap,
  int16 centimetres + float16 intensity + int32 instance id: 12 bytes a point, about
  1-50 kB a scan in traffic (100-4000 dynamic points).
- Coordinates beyond +-327.67 m in the sensor frame are dropped and counted
  (``dropped_out_of_range``). Intensity keeps about 3 significant digits (float16;
  values beyond +-65504 are clipped).

Intensity is the reader's value as it is (KITTI reflectance 0..1, AV2 0..255, ...);
scans without intensity (``Frame.intensity`` None) give 0, so the attribute is always
there.

Files (:func:`write_point_cloud`: Open3D tensor IO, binary, format from the suffix)
-----------------------------------------------------------------------------------
- ``static_map.ply`` / ``static_map.pcd``: float32 ``x y z`` (world frame, m) and float32
  ``intensity`` (voxel mean): PCL's ``PointXYZI``.
- ``dynamic_points.ply``: float32 ``x y z`` (world frame, m, each point where it was at
  its own scan), float32 ``intensity``, int32 ``instance`` (the frontend's instance id,
  -1 where it gives none) and int32 ``frame`` (dataset index of the scan).

Dynamic removal: only the points a frontend marks static go into the map, the others
into the dynamic points. A frontend without a static mask (``kiss-icp``; ``gt-flow``,
which does no segmentation) gives every point of each scan to the map: no dynamic
removal then, and no dynamic points (``StaticMapBuilder.removes_dynamic`` is False).
"""

from __future__ import annotations

import errno
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from flowslam import geometry

log = logging.getLogger(__name__)

__all__ = [
    "StaticMapBuilder", "DynamicPoints", "MapCloud", "write_point_cloud",
    "voxel_ids", "group_keys", "voxel_means", "voxel_downsample", "first_per_cell", "poses_by_index",
]

#: Storage resolution of the per-scan points (m) and the int16 range it allows.
STORAGE_RESOLUTION_M = 0.01
_INT16_MAX = 32767
_FLOAT16_MAX = float(np.finfo(np.float16).max)
_HEADER_ALLOWANCE = 1024
"""Bytes reserved for a PLY/PCD header on top of the point data (Open3D's are < 400)."""


def voxel_ids(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Group (N,3) points (N >= 1) by voxel: ``(inverse (N,) voxel of each point, counts (V,))``.

    Integer voxel coordinates packed into one int64 key (21 bits per axis relative to the
    minimum), grouped by :func:`group_keys` (both compiled: :mod:`flowslam.compiled_voxels`).
    Spans beyond 2^21 voxels per axis fall back to ``np.unique(axis=0)``. Voxels are
    numbered in key order (x, then y, then z).
    """
    from flowslam.compiled_voxels import grouped_keys, packed_voxel_keys

    keys, fits = packed_voxel_keys(points, voxel_size)
    if fits:
        return grouped_keys(keys)
    ijk = np.floor(np.asarray(points, dtype=np.float64) / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    return inverse.reshape(-1), counts


def group_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(inverse (N,), counts (V,))`` of (N,) int64 ``keys``, groups numbered in key order:
    what ``np.unique(keys, return_inverse=True, return_counts=True)`` returns, several times
    faster on scans (compiled: one pass through a hash table, then a sort of the distinct
    keys only; :mod:`flowslam.compiled_voxels`)."""
    from flowslam.compiled_voxels import grouped_keys

    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return grouped_keys(keys)


def voxel_means(
    points: np.ndarray, voxel_size: float, values: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """``(centroids (M,3), mean of values per voxel (M,) or None)`` of the occupied
    ``voxel_size`` voxels of (N,3) points (m) carrying (N,) ``values``; voxels in
    :func:`voxel_ids`' order, sums in point order."""
    from flowslam.compiled_voxels import group_means

    points = np.asarray(points, dtype=np.float64)
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0 (m), got {voxel_size}")
    if len(points) == 0:
        return np.zeros((0, 3)), None if values is None else np.zeros(0)
    inverse, counts = voxel_ids(points, voxel_size)
    if values is None:
        return group_means(inverse, counts, points), None
    columns = np.column_stack([points, np.asarray(values, dtype=np.float64).reshape(-1)])
    means = group_means(inverse, counts, columns)
    return np.ascontiguousarray(means[:, :3]), means[:, 3].copy()


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(M,3) centroids of the occupied ``voxel_size`` voxels of (N,3) points (vectorised)."""
    return voxel_means(points, voxel_size)[0]


def first_per_cell(points: np.ndarray, voxel_size: float, labels: np.ndarray) -> np.ndarray:
    """Sorted indices of one point (the first) per (voxel, label) cell of (N,3) points."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    inverse, _ = voxel_ids(np.asarray(points, dtype=np.float64), voxel_size)
    cells = inverse.astype(np.int64) * (1 << 32) + (np.asarray(labels, dtype=np.int64) & 0xFFFFFFFF)
    return np.sort(np.unique(cells, return_index=True)[1])


def poses_by_index(
    poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None
) -> dict[int, np.ndarray]:
    """``{scan index: T_world_sensor}`` from a dict, or from a (K,4,4) array with the
    scan index of each row (``indices``; default ``0..K-1``, e.g. ``RunResult.poses``
    with ``RunResult.indices``)."""
    if isinstance(poses, Mapping):
        return {int(k): np.asarray(v, dtype=np.float64) for k, v in poses.items()}
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"poses must be a dict or a (K,4,4) array; got shape {arr.shape}")
    idx = range(len(arr)) if indices is None else list(indices)
    if len(idx) != len(arr):
        raise ValueError(f"{len(idx)} indices for {len(arr)} poses")
    return {int(i): arr[k] for k, i in enumerate(idx)}


@dataclass
class MapCloud:
    """Points in the world frame (m) with their per-point attributes."""

    positions: np.ndarray
    """(M,3) float64, world frame, m."""
    intensity: np.ndarray
    """(M,) float32, the readers' intensity (0 where a scan had none)."""
    labels: dict[str, np.ndarray] = field(default_factory=dict)
    """Integer attributes, each (M,) (e.g. ``instance``, ``frame``), written as int32."""

    def __len__(self) -> int:
        return len(self.positions)


def write_point_cloud(path: str | Path, cloud: MapCloud) -> Path:
    """Write ``cloud`` as a binary PLY or PCD (from the suffix of ``path``) with Open3D's
    tensor IO: float32 ``x y z``, float32 ``intensity``, int32 labels. Returns ``path``.

    Open3D reports a failed write as a bare ``False`` (PCD) or not at all (a PLY cut at a
    file-size limit), so the file's size is first claimed through the OS: no space, a
    size limit or no permission is then an ``OSError`` naming the real reason here. An
    empty cloud is a ``ValueError`` (Open3D writes none)."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in (".ply", ".pcd"):
        raise ValueError(f"{path}: a point cloud is written as .ply or .pcd")
    if len(cloud) == 0:
        raise ValueError(f"{path}: no points to write")
    columns = {"intensity": np.asarray(cloud.intensity, dtype=np.float32)}
    columns.update({name: np.asarray(v, dtype=np.int32) for name, v in cloud.labels.items()})
    tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(cloud.positions, dtype=np.float32)))
    for name, values in columns.items():
        tensor.point[name] = o3d.core.Tensor(np.ascontiguousarray(values.reshape(-1, 1)))
    payload = len(cloud) * 4 * (3 + len(columns))
    _reserve(path, payload + _HEADER_ALLOWANCE)
    if not o3d.t.io.write_point_cloud(str(path), tensor):
        raise OSError(errno.EIO, "Open3D could not write the point cloud", str(path))
    if path.stat().st_size < payload:
        raise OSError(errno.EIO, "Open3D wrote an incomplete point cloud", str(path))
    return path


def _reserve(path: Path, nbytes: int) -> None:
    """Allocate ``nbytes`` for ``path`` (``posix_fallocate`` where there is one)."""
    with open(path, "wb") as f:
        if hasattr(os, "posix_fallocate"):
            os.posix_fallocate(f.fileno(), 0, nbytes)
        else:  # pragma: no cover - macOS, Windows
            f.truncate(nbytes)


@dataclass(slots=True)
class _Scan:
    """One scan's stored points: int16 centimetres (sensor frame), float16 intensity,
    int32 instance ids (or None)."""

    points: np.ndarray
    intensity: np.ndarray
    instance: np.ndarray | None = None


class _ScanStore:
    """Per-scan points (sensor frame) kept compactly (module doc); into the world with any poses."""

    def __init__(self, max_points_per_frame: int, seed: int, what: str):
        self.max_points_per_frame = int(max_points_per_frame)
        self.seed = seed
        self.what = what
        self.scans: dict[int, _Scan] = {}
        self.dropped_out_of_range = 0
        self.version = 0
        """Count of ``put`` calls (invalidates built clouds)."""

    def put(self, index: int, points: np.ndarray, intensity: np.ndarray, instance: np.ndarray | None = None) -> int:
        """Store (replace) scan ``index``: (n,3) points (m, sensor frame), (n,) intensity and
        instance ids, capped (seeded random subset) and quantised. Returns the points kept."""
        index = int(index)
        keep = self.capped(index, len(points))
        if keep is not None:
            points, intensity = points[keep], intensity[keep]
            instance = None if instance is None else instance[keep]
        q = np.round(points / STORAGE_RESOLUTION_M)
        ok = (np.abs(q) <= _INT16_MAX).all(axis=1)
        self.dropped_out_of_range += int(len(q) - np.count_nonzero(ok))
        self.scans[index] = _Scan(
            q[ok].astype(np.int16),
            np.clip(intensity[ok], -_FLOAT16_MAX, _FLOAT16_MAX).astype(np.float16),
            None if instance is None else np.asarray(instance)[ok].astype(np.int32),
        )
        self.version += 1
        return int(np.count_nonzero(ok))

    def capped(self, index: int, n: int) -> np.ndarray | None:
        """Sorted indices of the seeded random subset of ``n`` points that scan ``index``
        keeps under the cap, or None when all ``n`` fit."""
        if n <= self.max_points_per_frame:
            return None
        rng = np.random.default_rng([self.seed, int(index)])
        return np.sort(rng.choice(n, self.max_points_per_frame, replace=False))

    @property
    def n_points(self) -> int:
        return int(sum(len(s.points) for s in self.scans.values()))

    @property
    def nbytes(self) -> int:
        """Bytes of the stored point arrays."""
        return int(sum(s.points.nbytes + s.intensity.nbytes + (0 if s.instance is None else s.instance.nbytes)
                       for s in self.scans.values()))

    def points_of(self, index: int) -> np.ndarray:
        """Stored points of scan ``index`` (n,3), sensor frame, m."""
        return self.scans[int(index)].points.astype(np.float64) * STORAGE_RESOLUTION_M

    def world(self, lookup: Mapping[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every stored scan with a pose in ``lookup`` (``{index: T_world_sensor}``), in index
        order: ``(positions (M,3) world m, intensity (M,) float32, instance (M,) int32 (-1
        where none), frame (M,) int32)``. Scans without a pose are left out (logged)."""
        parts, missing = [], []
        for index in sorted(self.scans):
            if index not in lookup:
                missing.append(index)
                continue
            scan = self.scans[index]
            n = len(scan.points)
            instance = np.full(n, -1, np.int32) if scan.instance is None else scan.instance
            parts.append((geometry.transform_points(lookup[index], self.points_of(index)),
                          scan.intensity.astype(np.float32), instance, np.full(n, index, np.int32)))
        if missing:
            log.warning("%s: %d scan(s) without a pose left out (first: %d)", self.what, len(missing), missing[0])
        if not parts:
            return np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros(0, np.int32)
        return tuple(np.concatenate(column) for column in zip(*parts))


_KEY_BITS = 21
_KEY_HALF = 1 << (_KEY_BITS - 1)


def _world_voxel_keys(points_world: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """``(keys (N,) int64, valid (N,) bool)``: each point's ``voxel_size`` voxel packed into
    one int64 (21 bits per axis, +-2^20 voxels about the origin); ``valid`` is False
    beyond that range (those points are never deduplicated)."""
    v = np.floor(points_world / voxel_size).astype(np.int64) + _KEY_HALF
    valid = ((v >= 0) & (v < (1 << _KEY_BITS))).all(axis=1)
    v = np.where(valid[:, None], v, 0)
    return (v[:, 0] << (2 * _KEY_BITS)) | (v[:, 1] << _KEY_BITS) | v[:, 2], valid


class _RecentVoxels:
    """World voxels seen by the last ``window`` scans: sorted unique int64 keys and, for
    each, the newest scan index that saw it. Vectorised (``searchsorted``/``insert``);
    entries older than the window are pruned every ``window`` scans, so the size is
    bounded by about two windows of new voxels plus one scan."""

    def __init__(self, window: int):
        self.window = int(window)
        self.keys = np.zeros(0, np.int64)
        self.last = np.zeros(0, np.int64)
        self._pruned_at: int | None = None

    def observe(self, keys: np.ndarray, valid: np.ndarray, index: int,
                choose: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, int]:
        """Scan ``index`` sees voxels ``keys`` ((N,) int64; ``valid`` (N,) False: never
        deduplicated). Those seen by a scan in ``[index - window, index)`` are dropped;
        ``choose(candidates)`` picks which of the others (sorted indices) the scan keeps.
        What was seen before and what is kept are then recorded as seen by ``index``.
        Returns ``(kept indices (sorted), count dropped)``. One sort and one binary search
        of the scan's keys: O(N log N + N log M) for M recent keys, plus O(M) to insert."""
        n = len(keys)
        order = np.argsort(keys, kind="stable")
        ks, ok = keys[order], valid[order]
        m = len(self.keys)
        pos = np.searchsorted(self.keys, ks)
        hit = np.zeros(n, bool)
        if m:
            inside = pos < m
            hit[inside] = self.keys[pos[inside]] == ks[inside]
        last = np.where(hit, self.last[np.minimum(pos, max(m - 1, 0))] if m else 0, np.iinfo(np.int64).min)
        seen_sorted = hit & ok & (last < index) & (last >= index - self.window)
        seen = np.empty(n, bool)
        seen[order] = seen_sorted
        kept = choose(np.flatnonzero(~seen))
        observed = seen.copy()
        observed[kept] = True
        observed_sorted = observed[order] & ok
        update = observed_sorted & hit
        self.last[pos[update]] = np.maximum(self.last[pos[update]], index)
        new = observed_sorted & ~hit
        new_keys, new_pos = ks[new], pos[new]
        first = np.ones(len(new_keys), bool)
        first[1:] = new_keys[1:] != new_keys[:-1]  # one entry per voxel
        self.keys = np.insert(self.keys, new_pos[first], new_keys[first])
        self.last = np.insert(self.last, new_pos[first], index)
        if self._pruned_at is None or index - self._pruned_at >= self.window or index < self._pruned_at:
            keep = self.last >= index - self.window
            self.keys, self.last = self.keys[keep], self.last[keep]
            self._pruned_at = index
        return kept, int(np.count_nonzero(seen))

    @property
    def nbytes(self) -> int:
        return self.keys.nbytes + self.last.nbytes


def _intensity_or_zeros(intensity: np.ndarray | None, n: int) -> np.ndarray:
    if intensity is None or len(intensity) != n:
        return np.zeros(n)
    return np.asarray(intensity, dtype=np.float64).reshape(-1)


class DynamicPoints:
    """The points a frontend marked dynamic, per scan (module doc); world cloud with
    ``instance`` and ``frame`` labels from any set of poses."""

    def __init__(self, voxel_size: float = 0.2, max_points_per_frame: int = 30000, seed: int = 0):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0 (m), got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.store = _ScanStore(max_points_per_frame, seed, "dynamic points")

    def add(self, index: int, points_sensor: np.ndarray, intensity: np.ndarray | None = None,
            instance_ids: np.ndarray | None = None) -> int:
        """Keep scan ``index``'s dynamic points ((n,3) sensor frame, m) with their intensity
        and instance ids ((n,), None = 0 / -1): one per voxel and instance. Returns the count kept."""
        pts = np.asarray(points_sensor, dtype=np.float64).reshape(-1, 3)
        ids = np.full(len(pts), -1, np.int64) if instance_ids is None else np.asarray(instance_ids).reshape(-1)
        inten = _intensity_or_zeros(intensity, len(pts))
        finite = geometry.finite_rows(pts)
        pts, ids, inten = pts[finite], ids[finite], inten[finite]
        keep = first_per_cell(pts, self.voxel_size, ids)
        return self.store.put(index, pts[keep], inten[keep], ids[keep])

    @property
    def n_points(self) -> int:
        return self.store.n_points

    def cloud(self, poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None) -> MapCloud:
        """Every stored point in the world (its own scan's ``T_world_sensor``; ``poses`` as in
        :func:`poses_by_index`), not merged across scans."""
        positions, intensity, instance, frame = self.store.world(poses_by_index(poses, indices))
        return MapCloud(positions, intensity, {"instance": instance, "frame": frame})

    def write(self, path: str | Path, poses: Mapping[int, np.ndarray] | np.ndarray,
              indices: Sequence[int] | None = None) -> int:
        """Write ``dynamic_points.ply`` (module doc) with ``poses``; returns the point count."""
        cloud = self.cloud(poses, indices)
        write_point_cloud(path, cloud)
        return len(cloud)


class StaticMapBuilder:
    """Collects static points per scan (and, in ``dynamic``, the points marked dynamic);
    builds the world map from any set of poses."""

    def __init__(self, voxel_size: float = 0.2, max_points_per_frame: int = 30000, seed: int = 0,
                 dedup_window: int = 50):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0 (m), got {voxel_size}")
        if dedup_window < 0:
            raise ValueError(f"dedup_window must be >= 0 (scans), got {dedup_window}")
        self.voxel_size = float(voxel_size)
        self.store = _ScanStore(max_points_per_frame, seed, "static map")
        self.dedup_window = int(dedup_window)
        """Scans back within which a voxel already seen is not stored again (0: keep all)."""
        self._recent = _RecentVoxels(self.dedup_window)
        self._odometry: dict[int, np.ndarray] = {}
        """``T_world_sensor`` (odometry frame) of the last scans seen by ``on_output``."""
        self.deduplicated = 0
        """Voxel centroids not stored because a recent scan had seen their voxel."""
        self.dynamic = DynamicPoints(voxel_size, max_points_per_frame, seed)
        """The points the frontend marked dynamic (``dynamic_points.ply``)."""
        self.removes_dynamic = False
        """True once a frontend output carried a static mask (then ``dynamic`` is meaningful)."""
        self.skipped_outputs = 0
        """Frontend outputs without per-point results from a per-point frontend (no points added)."""
        self._per_point_frontend = False
        self._last: tuple[int, np.ndarray | None] | None = None
        """(index, intensity) of the last frame seen by ``on_output``."""
        self._built: tuple[tuple, MapCloud] | None = None

    @property
    def max_points_per_frame(self) -> int:
        return self.store.max_points_per_frame

    @property
    def frames(self) -> dict[int, np.ndarray]:
        """scan index -> (n,3) int16 points in its sensor frame, centimetres."""
        return {index: scan.points for index, scan in self.store.scans.items()}

    @property
    def dropped_out_of_range(self) -> int:
        return self.store.dropped_out_of_range

    # -- collecting -------------------------------------------------------------

    def add(self, index: int, points_sensor: np.ndarray, static_mask: np.ndarray | None = None,
            intensity: np.ndarray | None = None, T_world_sensor: np.ndarray | None = None) -> int:
        """Keep scan ``index``'s static points ((N,3) in its sensor frame, m; ``static_mask``
        (N,) bool or None = all; ``intensity`` (N,) or None = 0). Replaces an earlier entry
        of the same index. With ``T_world_sensor`` (the scan's odometry pose; scans in
        index order) only the voxels no recent earlier scan saw are kept (module doc).
        Returns the number of points kept."""
        pts = np.asarray(points_sensor, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (N,3); got {pts.shape}")
        keep = geometry.finite_rows(pts)
        if static_mask is not None:
            mask = np.asarray(static_mask, dtype=bool).reshape(-1)
            if mask.shape[0] != len(pts):
                raise ValueError(f"static_mask must be (N,) with N={len(pts)}; got {mask.shape}")
            keep &= mask
        centroids, inten = voxel_means(pts[keep], self.voxel_size, _intensity_or_zeros(intensity, len(pts))[keep])
        if T_world_sensor is None or self.dedup_window == 0:
            return self.store.put(index, centroids, inten)
        keys, valid = _world_voxel_keys(geometry.transform_points(T_world_sensor, centroids), self.voxel_size)

        def choose(new: np.ndarray) -> np.ndarray:  # the cap's seeded subset of the new voxels
            capped = self.store.capped(index, len(new))
            return new if capped is None else new[capped]

        kept, dropped = self._recent.observe(keys, valid, int(index), choose)
        self.deduplicated += dropped
        return self.store.put(index, centroids[kept], inten[kept])

    def on_output(self, frame, output) -> None:
        """``run_pipeline(on_output=...)`` adapter.

        Per-point outputs refer to the previous scan (``output.points``,
        ``output.static_mask``, ``output.instance_ids``), so they are stored under the
        previous scan's index, with that scan's intensity (kept from the last call). The
        points a static mask leaves out go to ``dynamic``. Until a frontend has given
        per-point outputs, each scan's own points are stored whole (``kiss-icp``: no
        dynamic removal); the first per-point output then replaces that entry.
        Consequently, with a flow frontend the last scan of a sequence (whose flow never
        comes) is not in the map.
        """
        last, self._last = self._last, (int(frame.index), frame.intensity)
        prev_index, prev_intensity = last if last is not None else (output.index - 1, None)
        pose_prev = self._odometry.get(prev_index)
        restart = pose_prev is None or output.T_prev_curr is None
        if restart:  # first scan, or no motion: a new odometry chain, nothing recent to compare with
            pose = np.eye(4)
            self._recent = _RecentVoxels(self.dedup_window)
        else:
            pose = pose_prev @ np.asarray(output.T_prev_curr, dtype=np.float64)
        self._odometry = {int(frame.index): pose} if restart else {prev_index: pose_prev, int(frame.index): pose}
        if output.points is not None:
            self._per_point_frontend = True
            self.add(prev_index, output.points, output.static_mask, prev_intensity, None if restart else pose_prev)
            if output.static_mask is not None:
                self._add_dynamic(prev_index, output, prev_intensity)
        elif self._per_point_frontend:
            self.skipped_outputs += 1
        else:
            self.add(frame.index, frame.points, None, frame.intensity, pose)

    def _add_dynamic(self, index: int, output, intensity: np.ndarray | None) -> None:
        self.removes_dynamic = True
        dynamic = ~np.asarray(output.static_mask, dtype=bool).reshape(-1)
        ids = None if output.instance_ids is None else np.asarray(output.instance_ids).reshape(-1)[dynamic]
        self.dynamic.add(index, np.asarray(output.points)[dynamic],
                         _intensity_or_zeros(intensity, len(dynamic))[dynamic], ids)

    @property
    def n_points(self) -> int:
        """Points stored over all scans."""
        return self.store.n_points

    def points_of(self, index: int) -> np.ndarray:
        """Stored points of scan ``index`` (n,3), sensor frame, m."""
        return self.store.points_of(index)

    # -- building ---------------------------------------------------------------

    def cloud(self, poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None) -> MapCloud:
        """The world-frame map: every stored scan mapped with its ``T_world_sensor`` (dict
        ``index -> pose``, or (K,4,4) with ``indices``, see :func:`poses_by_index`), then
        voxel-downsampled together (centroid, mean intensity). Scans without a pose are
        left out (logged). The last result is kept until the points or the poses change
        (``static_map.ply`` and ``.pcd`` build it once)."""
        lookup = poses_by_index(poses, indices)
        key = (self.store.version, tuple((i, lookup[i].tobytes()) for i in sorted(lookup) if i in self.store.scans))
        if self._built is None or self._built[0] != key:
            positions, intensity, _, _ = self.store.world(lookup)
            centroids, mean_intensity = voxel_means(positions, self.voxel_size, intensity)
            self._built = (key, MapCloud(centroids, mean_intensity.astype(np.float32)))
        return self._built[1]

    def build(
        self, poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None
    ) -> np.ndarray:
        """(M,3) world-frame map positions (m) of :meth:`cloud`."""
        return self.cloud(poses, indices).positions

    def write(
        self, path: str | Path, poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None
    ) -> int:
        """Build with ``poses`` and write ``path`` (``.ply`` or ``.pcd``, :func:`write_point_cloud`);
        returns the number of map points."""
        cloud = self.cloud(poses, indices)
        write_point_cloud(path, cloud)
        return len(cloud)
