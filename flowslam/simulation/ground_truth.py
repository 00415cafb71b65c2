"""From ray hits to a LiDAR frame with exact ground truth.

Definitions (``t0`` = this frame's timestamp, ``t1`` = the next frame's, ``tau`` =
the point's firing offset within the sweep: ``c / columns * sweep_period`` with
motion distortion, 0 without):

- ``points``: each return in the *sensor frame at its own firing time* ``t0 + tau``,
  as a raw spinning LiDAR reports it (``p = head_origin + range * ray_direction``).
  Without distortion all points share the sensor frame at ``t0``. Range noise is
  applied along the ray; the stored coordinates are float32 and the ground truth
  below is computed from exactly those float32 values.
- ``flow`` (Argoverse 2 convention): ``p + flow`` is the same physical point at
  ``t1 + tau`` (the same phase of the next sweep) expressed in the sensor frame at
  ``t1 + tau``. The physical point is the measured point rigidly attached to the
  object it hit (noise included): for the static world
  ``flow = inv(T_w_s(t1+tau)) T_w_s(t0+tau) p - p``; for an actor the point is
  carried by the actor's motion from ``t0 + tau`` to ``t1 + tau``.
- ``flow_compensated``: the object's own motion only, in the sensor frame at
  ``t0 + tau``: ``inv(R_w_s(t0+tau)) (P(t1+tau) - P(t0+tau))`` (zero for static points).
- ``dynamic``: the point's world displacement over ``t1 - t0`` exceeds
  ``DYNAMIC_SPEED`` (0.5 m/s, Argoverse 2's threshold) times that interval.
- ``deskew()``: the point's world position at its firing time, expressed in the
  sensor frame at ``t0`` (a perfectly motion-compensated scan), from the ego track.
- ``class``, ``instance``: see ``labels``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowslam.simulation import labels
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.raycast import Raycaster, RawScan

DYNAMIC_SPEED = 0.5
"""m/s: points moving faster than this in the world are ``dynamic``."""


@dataclass
class SimFrame:
    points: np.ndarray  # (N,3) float32
    intensity: np.ndarray  # (N,) float32
    times: np.ndarray  # (N,) float32, seconds after the frame timestamp
    flow: np.ndarray  # (N,3) float32
    flow_compensated: np.ndarray  # (N,3) float32
    dynamic: np.ndarray  # (N,) bool
    cls: np.ndarray  # (N,) uint8
    instance: np.ndarray  # (N,) int32
    beam: np.ndarray  # (N,) uint16
    column: np.ndarray  # (N,) uint16

    def arrays(self) -> dict[str, np.ndarray]:
        out = {
            "flow": self.flow, "flow_compensated": self.flow_compensated, "dynamic": self.dynamic,
            "class": self.cls, "instance": self.instance, "times": self.times, "beam": self.beam,
            "column": self.column,
        }
        return out


def _rot(x, y, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return c * x - s * y, s * x + c * y


def make_frame(raw: RawScan, caster: Raycaster, ego: PoseTrack, t0: float, t1: float, distortion: bool,
               rng: np.random.Generator) -> SimFrame:
    sensor = caster.sensor
    n = len(raw.t)
    r = raw.t
    if sensor.range_noise > 0:
        r = r + sensor.range_noise * rng.standard_normal(n, dtype=np.float32)
    keep = (r >= sensor.min_range) & (r <= sensor.max_range)
    if sensor.dropout > 0:
        keep &= rng.random(n, dtype=np.float32) >= sensor.dropout
    if not keep.all():
        sel = np.flatnonzero(keep)
        raw = RawScan(raw.ray[sel], raw.column[sel], raw.beam[sel], raw.t[sel], raw.actor[sel], raw.label[sel],
                      raw.cos_incidence[sel], raw.column_times)
        r = r[sel]
    col, beam, actor, label = raw.column, raw.beam, raw.actor, raw.label
    d = caster.flat_dirs[raw.ray]
    p = (caster.offsets[beam] + r[:, None] * d).astype(np.float32)
    p64 = p.astype(np.float64)
    px, py = p64[:, 0], p64[:, 1]
    # sensor poses at the firing time and at the same phase of the next sweep (per column,
    # gathered per point; cos/sin per column only)
    e0x, e0y, e0yaw = ego.at(t0 + raw.column_times)
    e1x, e1y, e1yaw = ego.at(t1 + raw.column_times)
    c0, s0 = np.cos(e0yaw)[col], np.sin(e0yaw)[col]
    c1, s1 = np.cos(e1yaw)[col], np.sin(e1yaw)[col]
    wx = c0 * px - s0 * py + e0x[col]
    wy = s0 * px + c0 * py + e0y[col]
    # class and instance
    cls = np.empty(len(r), dtype=np.uint8)
    static = actor < 0
    ground = label < 0  # only static hits can have a negative label
    cls[ground] = caster.world.ground_class(np.stack([wx[ground], wy[ground]], 1))
    things = static & ~ground
    cls[things] = caster.world.instance_class[label[things]]
    instance = np.where(ground, -1, label).astype(np.int32)
    # where each point is one frame later (static points stay)
    nx, ny = wx.copy(), wy.copy()
    actors = caster.actors
    moving = np.flatnonzero(~static)
    if len(moving):
        order = moving[np.argsort(actor[moving], kind="stable")]
        ks, starts = np.unique(actor[order], return_index=True)
        for k, m in zip(ks, np.split(order, starts[1:])):
            a = actors.actors[k]
            tau = raw.column_times[col[m]]
            ax, ay, ayaw = a.track.at(t0 + tau)
            bx, by, byaw = a.track.at(t1 + tau)
            lx, ly = _rot(wx[m] - ax, wy[m] - ay, -ayaw)
            qx, qy = _rot(lx, ly, byaw)
            nx[m], ny[m] = qx + bx, qy + by
            cls[m] = actors.shapes[a.shape].class_id
    # into the sensor frame at t1 + tau: p + flow; and the object's own motion in frame t0 + tau
    dx, dy = nx - e1x[col], ny - e1y[col]
    flow = np.empty((len(r), 3), dtype=np.float32)
    flow[:, 0] = c1 * dx + s1 * dy - px
    flow[:, 1] = -s1 * dx + c1 * dy - py
    flow[:, 2] = 0.0  # flat world, planar motion: (z + h) - h - z
    mx, my = nx - wx, ny - wy
    flow_c = np.zeros((len(r), 3), dtype=np.float32)
    if len(moving):
        flow_c[moving, 0] = c0[moving] * mx[moving] + s0[moving] * my[moving]
        flow_c[moving, 1] = -s0[moving] * mx[moving] + c0[moving] * my[moving]
    dynamic = np.zeros(len(r), dtype=bool)
    dynamic[moving] = np.hypot(mx[moving], my[moving]) > DYNAMIC_SPEED * (t1 - t0)
    refl = labels.REFLECTIVITY.astype(np.float32)[cls]
    inten = refl * (0.35 + 0.65 * np.minimum(raw.cos_incidence, 1.0)) * (1.0 - 0.4 / sensor.max_range * r)
    inten = np.clip(inten + 0.02 * rng.standard_normal(len(r), dtype=np.float32), 0.0, 1.0).astype(np.float32)
    return SimFrame(
        points=p, intensity=inten, times=raw.column_times[col].astype(np.float32), flow=flow,
        flow_compensated=flow_c, dynamic=dynamic, cls=cls, instance=instance,
        beam=beam.astype(np.uint16), column=col.astype(np.uint16),
    )


def deskew(points: np.ndarray, times: np.ndarray, ego: PoseTrack, t0: float) -> np.ndarray:
    """Points given in the sensor frame at ``t0 + times`` re-expressed in the sensor frame at
    ``t0`` (each point's world position at its own firing time): a perfect motion compensation."""
    x, y, yaw = ego.at(t0 + np.asarray(times, dtype=np.float64))
    x0, y0, yaw0 = (float(v) for v in ego.at(t0))
    p = np.asarray(points, dtype=np.float64)
    wx, wy = _rot(p[:, 0], p[:, 1], yaw)
    rx, ry = _rot(wx + x - x0, wy + y - y0, -yaw0)
    return np.stack([rx, ry, p[:, 2]], 1)
