"""2-D polylines parametrised by arc length, and planar pose tracks over time.

``Polyline``: points (M,2) in the town frame (metres), arc length ``s`` from the
first point; ``position(s)`` and ``heading(s)`` interpolate linearly (the heading
between per-vertex tangent angles, so it is continuous).

``PoseTrack``: a planar rigid motion sampled at increasing times (s):
``x, y, yaw`` (yaw unwrapped). ``at(t)`` interpolates linearly in x, y and yaw; this
interpolation *is* the ground-truth motion (the ray caster and the flow ground
truth both call it), so it is exact by construction. Outside the sampled span the
first/last state is held.
"""

from __future__ import annotations

import numpy as np


def wrap_angle(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class Polyline:
    def __init__(self, points: np.ndarray, closed: bool = False):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if closed and len(pts) > 1 and np.linalg.norm(pts[0] - pts[-1]) > 1e-9:
            pts = np.vstack([pts, pts[:1]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        pts = pts[keep]
        self.points = pts
        self.closed = closed
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        d = np.diff(pts, axis=0)
        seg_heading = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
        if len(seg_heading) == 0:
            vh = np.zeros(len(pts))
        else:
            # vertex tangent: mean direction of the adjacent segments, unwrapped along the line
            prev = np.concatenate([[seg_heading[0]], seg_heading])
            nxt = np.concatenate([seg_heading, [seg_heading[-1]]])
            if closed and len(seg_heading) > 1:
                prev[0] = seg_heading[-1]
                nxt[-1] = seg_heading[0]
            vh = prev + wrap_angle(nxt - prev) / 2
        self.vertex_heading = np.unwrap(vh)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def _locate(self, s):
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, max(len(self.s) - 2, 0))
        ds = self.s[i + 1] - self.s[i] if len(self.s) > 1 else np.ones_like(s)
        f = np.where(ds > 0, (s - self.s[i]) / np.where(ds > 0, ds, 1.0), 0.0)
        return i, f

    def position(self, s) -> np.ndarray:
        if len(self.points) == 1:
            return np.broadcast_to(self.points[0], np.shape(s) + (2,)).copy()
        i, f = self._locate(s)
        return self.points[i] + f[..., None] * (self.points[i + 1] - self.points[i])

    def heading(self, s) -> np.ndarray:
        if len(self.points) == 1:
            return np.zeros(np.shape(s))
        i, f = self._locate(s)
        return self.vertex_heading[i] + f * (self.vertex_heading[i + 1] - self.vertex_heading[i])

    def resampled(self, step: float) -> "Polyline":
        n = max(int(np.ceil(self.length / step)), 1)
        return Polyline(self.position(np.linspace(0.0, self.length, n + 1)), closed=self.closed)

    def offset(self, d: float) -> "Polyline":
        """Parallel line ``d`` metres to the left (negative: right), vertex normals from tangents."""
        h = self.vertex_heading
        n = np.stack([-np.sin(h), np.cos(h)], axis=1)
        return Polyline(self.points + d * n, closed=self.closed)

    def reversed(self) -> "Polyline":
        return Polyline(self.points[::-1], closed=self.closed)

    def sub(self, s0: float, s1: float, step: float = 0.5) -> "Polyline":
        n = max(int(np.ceil((s1 - s0) / step)), 1)
        return Polyline(self.position(np.linspace(s0, s1, n + 1)))

    def curvature(self) -> np.ndarray:
        """|d heading / d s| at each vertex (1/m)."""
        if len(self.points) < 3:
            return np.zeros(len(self.points))
        dh = np.gradient(self.vertex_heading, self.s)
        return np.abs(dh)


def concat_polylines(lines: list[Polyline]) -> Polyline:
    pts = [lines[0].points]
    for ln in lines[1:]:
        p = ln.points
        if np.linalg.norm(p[0] - pts[-1][-1]) < 1e-6:
            p = p[1:]
        pts.append(p)
    return Polyline(np.concatenate(pts))


def quad_bezier(p0, p1, p2, step: float = 0.5) -> np.ndarray:
    p0, p1, p2 = (np.asarray(p, dtype=np.float64) for p in (p0, p1, p2))
    approx = np.linalg.norm(p1 - p0) + np.linalg.norm(p2 - p1)
    n = max(int(np.ceil(approx / step)), 2)
    u = np.linspace(0, 1, n + 1)[:, None]
    return (1 - u) ** 2 * p0 + 2 * (1 - u) * u * p1 + u**2 * p2


class PoseTrack:
    """Planar motion sampled at times ``t`` (S,): ``x, y, yaw`` (module doc)."""

    def __init__(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray):
        self.t = np.asarray(t, dtype=np.float64)
        self.x = np.asarray(x, dtype=np.float64)
        self.y = np.asarray(y, dtype=np.float64)
        self.yaw = np.unwrap(np.asarray(yaw, dtype=np.float64))
        if len(self.t) > 1 and np.any(np.diff(self.t) <= 0):
            raise ValueError("PoseTrack times must increase")
        self._uniform = len(self.t) > 2 and np.allclose(np.diff(self.t), self.t[1] - self.t[0], rtol=0, atol=1e-9)

    def __len__(self) -> int:
        return len(self.t)

    def _locate(self, t):
        t = np.asarray(t, dtype=np.float64)
        if len(self.t) == 1:
            return np.zeros(t.shape, dtype=np.int64), np.zeros(t.shape)
        tc = np.clip(t, self.t[0], self.t[-1])
        if self._uniform:
            dt = self.t[1] - self.t[0]
            i = np.clip(np.floor((tc - self.t[0]) / dt).astype(np.int64), 0, len(self.t) - 2)
        else:
            i = np.clip(np.searchsorted(self.t, tc, side="right") - 1, 0, len(self.t) - 2)
        f = (tc - self.t[i]) / (self.t[i + 1] - self.t[i])
        return i, f

    def at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) at time(s) ``t`` (linear interpolation; held outside the span)."""
        i, f = self._locate(t)
        if len(self.t) == 1:
            return (np.full(np.shape(t), self.x[0]), np.full(np.shape(t), self.y[0]), np.full(np.shape(t), self.yaw[0]))
        j = i + 1
        return (self.x[i] + f * (self.x[j] - self.x[i]), self.y[i] + f * (self.y[j] - self.y[i]),
                self.yaw[i] + f * (self.yaw[j] - self.yaw[i]))

    def speed(self) -> np.ndarray:
        """(S-1,) speed of each sample interval (m/s)."""
        return np.hypot(np.diff(self.x), np.diff(self.y)) / np.diff(self.t)

    def as_array(self) -> np.ndarray:
        return np.stack([self.t, self.x, self.y, self.yaw], axis=1)


def planar_T(x, y, yaw, z: float = 0.0) -> np.ndarray:
    """4x4 transform(s) ``T_world_body`` of planar pose(s) at height ``z``."""
    x, y, yaw = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(yaw, float))
    T = np.zeros(x.shape + (4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 2, 2] = 1.0
    T[..., 0, 3], T[..., 1, 3], T[..., 2, 3] = x, y, z
    T[..., 3, 3] = 1.0
    return T
