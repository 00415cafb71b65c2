"""Triangle meshes: primitives (box, prism, ellipsoid), and the actor shape library.

A ``Mesh`` is numpy arrays only (vertices (V,3) float64, triangles (T,3) int32,
``labels`` (T,) int64, one tag per triangle), so towns are assembled by
concatenation and only the ray caster touches Open3D.

Actor shapes live in their *local frame*: x forward, y left, z up, origin on the
ground at the centre of the footprint (length along x, width along y).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowslam.simulation import labels


@dataclass
class Mesh:
    vertices: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray

    @staticmethod
    def empty() -> "Mesh":
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.int64))

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)

    def with_label(self, label: int) -> "Mesh":
        return Mesh(self.vertices, self.triangles, np.full(len(self.triangles), label, dtype=np.int64))

    def transformed(self, yaw: float = 0.0, t=(0.0, 0.0, 0.0), scale=1.0) -> "Mesh":
        """Scale (scalar or per axis), then rotate by ``yaw`` about z, then translate."""
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        v = (self.vertices * np.asarray(scale, dtype=np.float64)) @ R.T + np.asarray(t, dtype=np.float64)
        return Mesh(v, self.triangles, self.labels)

    @staticmethod
    def concat(meshes: list["Mesh"]) -> "Mesh":
        meshes = [m for m in meshes if m.num_triangles]
        if not meshes:
            return Mesh.empty()
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]).astype(np.int32),
            np.concatenate([m.labels for m in meshes]),
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


_BOX_TRIS = np.array(
    [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]],
    dtype=np.int32,
)


def box(size, center=(0.0, 0.0, 0.0), yaw: float = 0.0, label: int = 0) -> Mesh:
    """Axis-aligned (then yawed) box of ``size`` (lx, ly, lz) centred at ``center``."""
    lx, ly, lz = (float(s) / 2 for s in size)
    v = np.array([[-lx, -ly, -lz], [lx, -ly, -lz], [lx, ly, -lz], [-lx, ly, -lz],
                  [-lx, -ly, lz], [lx, -ly, lz], [lx, ly, lz], [-lx, ly, lz]])
    return Mesh(v, _BOX_TRIS.copy(), np.full(12, label, dtype=np.int64)).transformed(yaw, center)


def prism(radius: float, height: float, sides: int = 8, center=(0.0, 0.0, 0.0), label: int = 0) -> Mesh:
    """Closed n-gon prism (a cylinder) standing on z, base centre at ``center``."""
    a = np.arange(sides) * (2 * np.pi / sides)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    v = np.concatenate([np.column_stack([ring, np.zeros(sides)]), np.column_stack([ring, np.full(sides, height)]),
                        [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    i = np.arange(sides)
    j = (i + 1) % sides
    sidewall = np.concatenate([np.stack([i, j, j + sides], 1), np.stack([i, j + sides, i + sides], 1)])
    bottom = np.stack([np.full(sides, 2 * sides), j, i], 1)
    top = np.stack([np.full(sides, 2 * sides + 1), i + sides, j + sides], 1)
    tris = np.concatenate([sidewall, bottom, top]).astype(np.int32)
    return Mesh(v + np.asarray(center, dtype=np.float64), tris, np.full(len(tris), label, dtype=np.int64))


def ellipsoid(radii, center=(0.0, 0.0, 0.0), n_lat: int = 6, n_lon: int = 10, label: int = 0) -> Mesh:
    """UV ellipsoid with semi-axes ``radii`` centred at ``center``."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)[1:-1]
    lon = np.arange(n_lon) * (2 * np.pi / n_lon)
    cl, sl = np.cos(lat)[:, None], np.sin(lat)[:, None]
    ring = np.stack([cl * np.cos(lon), cl * np.sin(lon), np.broadcast_to(sl, (len(lat), n_lon))], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 0, -1.0]], ring, [[0, 0, 1.0]]]) * np.asarray(radii, dtype=np.float64)
    south, north = 0, len(v) - 1
    tris = []
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    tris.append(np.stack([np.full(n_lon, south), 1 + jn, 1 + j], 1))
    for r in range(len(lat) - 1):
        a, b = 1 + r * n_lon, 1 + (r + 1) * n_lon
        tris.append(np.stack([a + j, a + jn, b + jn], 1))
        tris.append(np.stack([a + j, b + jn, b + j], 1))
    last = 1 + (len(lat) - 1) * n_lon
    tris.append(np.stack([np.full(n_lon, north), last + j, last + jn], 1))
    tris = np.concatenate(tris).astype(np.int32)
    return Mesh(v + np.asarray(center, dtype=np.float64), tris, np.full(len(tris), label, dtype=np.int64))


# ------------------------------------------------------------------ actor shapes
@dataclass(frozen=True)
class ActorShape:
    """A rigid actor body in its local frame (module doc) with its footprint size."""

    name: str
    kind: str
    """"car", "truck", "cyclist" or "pedestrian"."""
    class_id: int
    length: float
    width: float
    height: float
    mesh: Mesh

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere around (0, 0, height/2)."""
        return float(np.max(np.linalg.norm(self.mesh.vertices - [0, 0, self.height / 2], axis=1)))


def car_mesh(length: float, width: float, height: float, cabin: float = 0.55) -> Mesh:
    """Low-poly passenger car: wheels, a lower body and a cabin, facing +x."""
    wheel_r = 0.32
    body_top = 0.45 * height + 0.3
    parts = [box((length, width, body_top - 0.28), (0, 0, (body_top + 0.28) / 2))]
    cl = cabin * length
    parts.append(box((cl, 0.9 * width, height - body_top), (-0.06 * length, 0, (height + body_top) / 2)))
    for sx in (0.33, -0.33):
        for sy in (1, -1):
            parts.append(box((2 * wheel_r, 0.22, 2 * wheel_r), (sx * length, sy * (width / 2 - 0.11), wheel_r)))
    return Mesh.concat(parts)


def truck_mesh(length: float, width: float, height: float) -> Mesh:
    """Box truck: a cab in front and a taller cargo box behind."""
    cab = 2.0
    parts = [
        box((cab, width, 0.8 * height - 0.4), (length / 2 - cab / 2, 0, 0.4 + (0.8 * height - 0.4) / 2)),
        box((length - cab - 0.2, width, height - 0.5), (-(cab + 0.2) / 2, 0, 0.5 + (height - 0.5) / 2)),
    ]
    for sx in (0.38, -0.2, -0.38):
        for sy in (1, -1):
            parts.append(box((1.0, 0.3, 1.0), (sx * length, sy * (width / 2 - 0.15), 0.5)))
    return Mesh.concat(parts)


def cyclist_mesh(height: float = 1.75) -> Mesh:
    """Bicycle with rider, facing +x (1.8 m long)."""
    k = height / 1.75
    parts = [
        box((0.7, 0.06, 0.7), (0.55, 0, 0.35)),  # front wheel
        box((0.7, 0.06, 0.7), (-0.55, 0, 0.35)),  # rear wheel
        box((1.0, 0.08, 0.12), (0.0, 0, 0.75)),  # frame
        box((0.3, 0.3, 0.5 * k), (-0.05, 0, 0.75 + 0.25 * k)),  # legs/hips
        box((0.45, 0.38, 0.55 * k), (0.05, 0, 1.0 * k + 0.3 * k), yaw=0.0),  # torso
        ellipsoid((0.11, 0.1, 0.13), (0.15, 0, 1.62 * k), 4, 8),  # head
        box((0.5, 0.5, 0.05), (0.45, 0, 1.05 * k)),  # arms/handlebar
    ]
    return Mesh.concat(parts)


def pedestrian_mesh(height: float = 1.75) -> Mesh:
    """Standing person, facing +x: legs, torso, arms, head."""
    k = height / 1.75
    leg = 0.85 * k
    parts = [
        box((0.16, 0.14, leg), (0.0, 0.1, leg / 2)),
        box((0.16, 0.14, leg), (0.0, -0.1, leg / 2)),
        box((0.24, 0.40, 0.58 * k), (0.0, 0.0, leg + 0.29 * k)),
        box((0.12, 0.09, 0.6 * k), (0.0, 0.26, leg + 0.25 * k)),
        box((0.12, 0.09, 0.6 * k), (0.0, -0.26, leg + 0.25 * k)),
        ellipsoid((0.1, 0.09, 0.12), (0.0, 0.0, 1.62 * k), 4, 8),
    ]
    return Mesh.concat(parts)


def _shape(name, kind, cls, length, width, height, mesh) -> ActorShape:
    return ActorShape(name, kind, cls, length, width, height, mesh.with_label(0))


def shape_library() -> list[ActorShape]:
    """All actor shapes (moving actors and parked cars), indexed by position."""
    return [
        _shape("sedan", "car", labels.CAR, 4.5, 1.8, 1.45, car_mesh(4.5, 1.8, 1.45)),
        _shape("hatchback", "car", labels.CAR, 4.0, 1.75, 1.5, car_mesh(4.0, 1.75, 1.5, cabin=0.62)),
        _shape("suv", "car", labels.CAR, 4.8, 1.95, 1.75, car_mesh(4.8, 1.95, 1.75, cabin=0.6)),
        _shape("van", "car", labels.CAR, 5.2, 2.0, 2.1, car_mesh(5.2, 2.0, 2.1, cabin=0.75)),
        _shape("box-truck", "truck", labels.TRUCK, 7.0, 2.3, 3.2, truck_mesh(7.0, 2.3, 3.2)),
        _shape("truck", "truck", labels.TRUCK, 8.5, 2.4, 3.5, truck_mesh(8.5, 2.4, 3.5)),
        _shape("cyclist", "cyclist", labels.CYCLIST, 1.8, 0.6, 1.75, cyclist_mesh(1.75)),
        _shape("pedestrian-s", "pedestrian", labels.PEDESTRIAN, 0.3, 0.6, 1.6, pedestrian_mesh(1.6)),
        _shape("pedestrian-m", "pedestrian", labels.PEDESTRIAN, 0.3, 0.6, 1.75, pedestrian_mesh(1.75)),
        _shape("pedestrian-l", "pedestrian", labels.PEDESTRIAN, 0.3, 0.62, 1.9, pedestrian_mesh(1.9)),
    ]


def shapes_of_kind(library: list[ActorShape], kind: str) -> list[int]:
    return [i for i, s in enumerate(library) if s.kind == kind]
