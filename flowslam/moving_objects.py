"""Moving objects per scan from scene flow and instance ids: centroid, velocity, size.

Velocity (SSF-PAN Eq. 7 could not be retrieved; this is the definition used, which
is the usual one): the mean over an instance's dynamic points of the
**ego-motion-compensated flow**, divided by the time between the two scans,
expressed in the world frame.

Derivation (frames as in :mod:`flowslam.interfaces`): ``p`` is a point of scan
``k-1`` in sensor frame ``k-1``; ``q = p + f`` is the same physical point at scan
``k`` in sensor frame ``k``. In frame ``k-1`` that position is ``T_prev_curr q``, so
the object's own displacement, with the ego motion removed, is

    d = T_prev_curr (p + f) - p        (metres, sensor frame k-1)

(zero for a static point). The instance velocity is ``v = mean(d) / dt`` in frame
``k-1``, and ``R_world_{k-1} v`` in the world; the centroid is ``mean(p)`` in frame
``k-1`` and ``T_world_{k-1} mean(p)`` in the world. Rows are stamped with scan
``k-1`` (index and timestamp), whose points they describe.
"""

from __future__ import annotations

import csv
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from flowslam import geometry
from flowslam.mapping import poses_by_index

log = logging.getLogger(__name__)

__all__ = ["MovingObject", "MovingObjectsLog", "ego_compensated_flow", "moving_objects", "CSV_HEADER"]

CSV_HEADER = ("frame", "timestamp", "instance_id", "n_points", "cx", "cy", "cz", "vx", "vy", "vz", "speed",
              "track_id", "track_age", "sx", "sy", "sz")


@dataclass
class MovingObject:
    """One moving instance seen in scan ``frame`` (sensor frame of that scan, m, m/s)."""

    frame: int
    timestamp: float
    instance_id: int
    n_points: int
    centroid: np.ndarray
    """(3,) mean of the instance's dynamic points, sensor frame of scan ``frame`` (m)."""
    velocity: np.ndarray
    """(3,) ego-compensated velocity, sensor frame of scan ``frame`` (m/s)."""
    size: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) extent of the instance's dynamic points along the sensor axes (axis-aligned box, m)."""
    track_id: int = -1
    """The object's id across scans (:class:`flowslam.object_tracks.ObjectTracker`); -1: untracked."""
    track_age: int = 0
    """Scans since its track began (0: first seen in this scan)."""

    def in_world(self, T_world_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(centroid, velocity) in the world frame, given scan ``frame``'s pose."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        return T[:3, :3] @ self.centroid + T[:3, 3], T[:3, :3] @ self.velocity


def ego_compensated_flow(points: np.ndarray, flow: np.ndarray, T_prev_curr: np.ndarray) -> np.ndarray:
    """(N,3) displacement of each point in the world, expressed in sensor frame k-1 (m):
    ``T_prev_curr (p + f) - p`` (module doc)."""
    points = np.asarray(points, dtype=np.float64)
    return geometry.transform_points(T_prev_curr, points + np.asarray(flow, dtype=np.float64)) - points


def moving_objects(
    points: np.ndarray,
    flow: np.ndarray,
    instance_ids: np.ndarray,
    T_prev_curr: np.ndarray,
    dt: float,
    static_mask: np.ndarray | None = None,
    *,
    frame: int = -1,
    timestamp: float = float("nan"),
    min_points: int = 1,
    min_speed: float = 0.0,
) -> list[MovingObject]:
    """Moving instances of one scan pair (frames and velocity: module doc).

    Parameters
    ----------
    points, flow:
        (N,3) points of scan k-1 (sensor frame k-1, m) and their flow (AV2 convention).
    instance_ids:
        (N,) int, -1 = no instance.
    T_prev_curr:
        (4,4) ego motion, scan k into frame k-1.
    dt:
        Time between the scans (s), > 0.
    static_mask:
        (N,) bool; only the non-static points of an instance count. ``None``: every
        point with an instance id counts (then ``min_speed`` is the way to drop
        parked objects).
    frame, timestamp:
        Index and timestamp (s) of scan k-1, copied into the rows.
    min_points, min_speed:
        Instances with fewer dynamic points, or slower (m/s), are left out.
    """
    if not dt > 0:
        raise ValueError(f"dt must be > 0 (s), got {dt}")
    ids = np.asarray(instance_ids).reshape(-1).astype(np.int64)
    sel = ids >= 0
    if static_mask is not None:
        sel &= ~np.asarray(static_mask, dtype=bool).reshape(-1)
    flow = np.asarray(flow, dtype=np.float64)
    sel &= geometry.finite_rows(flow)
    if not np.any(sel):
        return []
    p = np.asarray(points, dtype=np.float64)[sel]
    d = ego_compensated_flow(p, flow[sel], T_prev_curr)
    uid, inverse, counts = np.unique(ids[sel], return_inverse=True, return_counts=True)
    V = len(uid)
    centroid = np.stack([np.bincount(inverse, p[:, i], V) for i in range(3)], axis=1) / counts[:, None]
    velocity = np.stack([np.bincount(inverse, d[:, i], V) for i in range(3)], axis=1) / counts[:, None] / dt
    lo, hi = np.full((V, 3), np.inf), np.full((V, 3), -np.inf)
    np.minimum.at(lo, inverse, p)
    np.maximum.at(hi, inverse, p)
    speed = np.linalg.norm(velocity, axis=1)
    keep = (counts >= min_points) & (speed >= min_speed)
    return [
        MovingObject(int(frame), float(timestamp), int(uid[j]), int(counts[j]), centroid[j], velocity[j], hi[j] - lo[j])
        for j in np.flatnonzero(keep)
    ]


class MovingObjectsLog:
    """Accumulates :class:`MovingObject` rows over a run; writes them as CSV in the world frame."""

    def __init__(self, min_points: int = 1, min_speed: float = 0.0, tracker=None, min_track_scans: int = 1):
        """``tracker``: an :class:`flowslam.object_tracks.ObjectTracker` (default: its
        defaults) that gives the objects of successive scans their track ids;
        ``min_track_scans``: :meth:`rows` (the CSV, the tracks) leaves out the objects of
        tracks seen in fewer scans (``objects`` keeps every one)."""
        from flowslam.object_tracks import ObjectTracker

        self.min_points = min_points
        self.min_speed = min_speed
        self.min_track_scans = min_track_scans
        self.tracker = tracker or ObjectTracker()
        self.objects: list[MovingObject] = []
        self._last: tuple[int, float] | None = None
        self._T_odom = np.eye(4)
        """Pose of the last scan in the odometry frame (its ``T_prev_curr`` chained)."""

    def add(self, objects: list[MovingObject]) -> None:
        self.objects.extend(objects)

    def on_output(self, frame, output) -> None:
        """``run_pipeline(on_output=...)`` adapter: logs the moving instances of the previous
        scan when the output has points, flow, instance ids and a motion, with their track
        ids (the tracker works in the frame of the chained ``T_prev_curr``)."""
        last, self._last = self._last, (int(frame.index), float(frame.timestamp))
        T_odom_prev = self._T_odom
        if output.T_prev_curr is not None:
            self._T_odom = T_odom_prev @ output.T_prev_curr
        if (
            last is None or output.T_prev_curr is None or output.points is None
            or output.flow is None or output.instance_ids is None
        ):
            return
        dt = float(frame.timestamp) - last[1]
        if not dt > 0:
            log.warning("moving objects: scan %d has a non-increasing timestamp; skipped", frame.index)
            return
        objects = moving_objects(
            output.points, output.flow, output.instance_ids, output.T_prev_curr, dt, output.static_mask,
            frame=last[0], timestamp=last[1], min_points=self.min_points, min_speed=self.min_speed,
        )
        self.tracker.assign(objects, last[0], last[1], T_odom_prev)
        self.add(objects)

    def rows(
        self, poses: Mapping[int, np.ndarray] | np.ndarray | None = None, indices: Sequence[int] | None = None
    ) -> list[tuple]:
        """CSV rows (``CSV_HEADER`` order), world frame via ``poses`` (see
        :func:`flowslam.mapping.poses_by_index`); ``poses=None`` keeps each scan's sensor
        frame. Objects of scans without a pose are left out (logged), and those of tracks
        seen in fewer than ``min_track_scans`` scans (untracked objects stay)."""
        lookup = None if poses is None else poses_by_index(poses, indices)
        seen = Counter(ob.track_id for ob in self.objects)
        out, missing = [], 0
        for ob in self.objects:
            if ob.track_id >= 0 and seen[ob.track_id] < self.min_track_scans:
                continue
            if lookup is None:
                c, v = ob.centroid, ob.velocity
            elif ob.frame in lookup:
                c, v = ob.in_world(lookup[ob.frame])
            else:
                missing += 1
                continue
            out.append((ob.frame, ob.timestamp, ob.instance_id, ob.n_points, *c, *v, float(np.linalg.norm(v)),
                        ob.track_id, ob.track_age, *ob.size))
        if missing:
            log.warning("moving objects: %d row(s) without a pose left out", missing)
        return out

    def tracks(self, poses: Mapping[int, np.ndarray] | np.ndarray, indices: Sequence[int] | None = None
               ) -> dict[int, np.ndarray]:
        """Track id -> (M,3) world centroids (m) of its objects in scan order, via ``poses``
        (as :meth:`rows`); untracked objects are left out."""
        out: dict[int, list] = {}
        for r in self.rows(poses, indices):
            if r[11] >= 0:
                out.setdefault(r[11], []).append(r[4:7])
        return {track: np.array(centres) for track, centres in out.items()}

    def write_csv(
        self,
        path: str | Path,
        poses: Mapping[int, np.ndarray] | np.ndarray | None = None,
        indices: Sequence[int] | None = None,
    ) -> Path:
        """Write ``CSV_HEADER``: frame, timestamp (s), the frontend's instance id, points,
        centroid and velocity (world frame with ``poses``; m, m/s), speed (m/s), track id,
        track age (scans), extent along the scan's sensor axes (m)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(CSV_HEADER)
            for r in self.rows(poses, indices):
                w.writerow([r[0], f"{r[1]:.6f}", r[2], r[3], *(f"{x:.4f}" for x in r[4:11]), r[11], r[12],
                            *(f"{x:.3f}" for x in r[13:])])
        return path
