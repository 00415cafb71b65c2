"""The static world around a road network: ground classes, buildings, walls, fences,
trees, poles and parked cars, as one labelled triangle mesh.

Ground: the plane z = 0. Its class (road / sidewalk / terrain) comes from a raster
of the distance to the nearest road centreline (``CLASS_RESOLUTION`` m cells):
road within ``HALF_WIDTH``, sidewalk up to ``BUILDING_LINE``, terrain beyond (and
outside the raster). Everything else is placed along iso-lines of that distance
(the same lines the pedestrians walk on), so objects keep to their strip of the
cross-section (see ``roads``) at bends and corners too:

- buildings: boxes facing the road behind the sidewalk (set back 0.3-3 m);
- walls and fences: on the property line where there is no building;
- trees and street lights: on the furniture line, 0.8 m behind the curb;
- parked cars: in the parking strips, clear of every driving lane and crosswalk;
- a few trees inside the blocks.

Every triangle's label is an instance id (``StaticWorld.instance_class[id]`` gives its
class); the ground has instance -1. ``StaticWorld.footprints`` lists each object's
oriented footprint (for the actors' collision checks).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from flowslam.simulation import labels
from flowslam.simulation.meshes import Mesh, box, ellipsoid, prism, shape_library, shapes_of_kind
from flowslam.simulation.paths import Polyline
from flowslam.simulation.roads import (
    BUILDING_LINE,
    FURNITURE,
    HALF_WIDTH,
    PARKING_WIDTH,
    WALK_LINES,
    RoadNetwork,
)

CLASS_RESOLUTION = 0.25
"""Cell size (m) of the ground-class raster."""


@dataclass
class TownStyle:
    building_height: tuple[float, float] = (5.0, 22.0)
    building_width: tuple[float, float] = (8.0, 26.0)
    building_depth: tuple[float, float] = (8.0, 18.0)
    building_gap: tuple[float, float] = (0.5, 7.0)
    building_prob: float = 0.85
    setback: tuple[float, float] = (0.3, 3.0)
    fence_prob: float = 0.6
    tree_spacing: tuple[float, float] = (7.0, 16.0)
    tree_prob: float = 0.75
    pole_spacing: float = 28.0
    parked_fill: float = 0.45
    inner_trees_per_hectare: float = 12.0
    margin: float = 70.0


@dataclass
class StaticWorld:
    mesh: Mesh
    instance_class: np.ndarray
    """(K,) class id of each static instance id (index = id; 0 unused)."""
    instance_kind: list[str]
    class_raster: np.ndarray
    """(H, W) uint8 ground class; cell (r, c) covers x = x0 + c*res .. , y = y0 + r*res .."""
    origin: np.ndarray
    resolution: float
    footprints: np.ndarray
    """(F, 6) [cx, cy, yaw, half_length, half_width, instance] of obstacles on the ground."""
    walk_loops: list[Polyline] = field(default_factory=list)
    parked: list = field(default_factory=list)

    def ground_class(self, xy: np.ndarray) -> np.ndarray:
        """Ground class at world points (N,2) from the raster (terrain outside it)."""
        c = np.floor((xy[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        r = np.floor((xy[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        h, w = self.class_raster.shape
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        out = np.full(len(xy), labels.TERRAIN, dtype=np.uint8)
        out[inside] = self.class_raster[r[inside], c[inside]]
        return out


class _Grid:
    """Distance-to-road raster with bilinear lookup, an occupancy raster, contours."""

    def __init__(self, net: RoadNetwork, margin: float, res: float):
        lo, hi = net.bounds()
        self.origin = lo - margin
        self.res = res
        size = np.ceil((hi + margin - self.origin) / res).astype(int) + 1
        self.shape = (int(size[1]), int(size[0]))
        samples = net.centerline_samples(res / 2)
        c = np.floor((samples[:, 0] - self.origin[0]) / res).astype(int)
        r = np.floor((samples[:, 1] - self.origin[1]) / res).astype(int)
        ok = (r >= 0) & (r < self.shape[0]) & (c >= 0) & (c < self.shape[1])
        free = np.ones(self.shape, dtype=bool)
        free[r[ok], c[ok]] = False
        sample_at = np.zeros(self.shape + (2,), dtype=np.float32)
        sample_at[r[ok], c[ok]] = samples[ok]
        _, ind = ndimage.distance_transform_edt(free, return_indices=True)
        near = sample_at[ind[0], ind[1]]
        del ind
        yy = self.origin[1] + (np.arange(self.shape[0], dtype=np.float32) + 0.5) * res
        xx = self.origin[0] + (np.arange(self.shape[1], dtype=np.float32) + 0.5) * res
        near[..., 0] -= xx[None, :]
        near[..., 1] -= yy[:, None]
        self.dist = np.hypot(near[..., 0], near[..., 1]).astype(np.float32)
        del near
        self.occupied = np.zeros(self.shape, dtype=bool)

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear distance to the nearest centreline at points (N,2)."""
        u = (xy[:, 0] - self.origin[0]) / self.res - 0.5
        v = (xy[:, 1] - self.origin[1]) / self.res - 0.5
        return ndimage.map_coordinates(self.dist, [v, u], order=1, mode="nearest")

    def away(self, xy: np.ndarray) -> np.ndarray:
        """Unit vectors pointing away from the road (distance gradient) at points (N,2)."""
        e = 0.5
        gx = self.lookup(xy + [e, 0]) - self.lookup(xy - [e, 0])
        gy = self.lookup(xy + [0, e]) - self.lookup(xy - [0, e])
        g = np.stack([gx, gy], 1)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)

    def contours(self, level: float, step: float = 0.5, closed_only: bool = False) -> list[Polyline]:
        import contourpy

        gen = contourpy.contour_generator(z=self.dist, line_type="SeparateCode")
        lines, codes = gen.lines(level)
        out = []
        for pts, code in zip(lines, codes):
            closed = code[-1] == 79  # CLOSEPOLY
            if closed_only and not closed:
                continue
            world = self.origin + (pts + 0.5) * self.res  # contourpy: x = column, y = row
            pl = Polyline(world, closed=closed)
            if pl.length > 4 * step:
                out.append(pl.resampled(step))
        return out

    def rect_cells(self, center, yaw, half_l, half_w, pad: float = 0.0):
        """Row/column indices of the cells whose centres lie in the oriented rectangle."""
        c, s = np.cos(yaw), np.sin(yaw)
        ext = abs(half_l * c) + abs(half_w * s) + pad, abs(half_l * s) + abs(half_w * c) + pad
        c0 = max(int((center[0] - ext[0] - self.origin[0]) / self.res), 0)
        c1 = min(int((center[0] + ext[0] - self.origin[0]) / self.res) + 1, self.shape[1])
        r0 = max(int((center[1] - ext[1] - self.origin[1]) / self.res), 0)
        r1 = min(int((center[1] + ext[1] - self.origin[1]) / self.res) + 1, self.shape[0])
        if c1 <= c0 or r1 <= r0:
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
        rr, cc = np.mgrid[r0:r1, c0:c1]
        x = self.origin[0] + (cc + 0.5) * self.res - center[0]
        y = self.origin[1] + (rr + 0.5) * self.res - center[1]
        lx, ly = c * x + s * y, -s * x + c * y
        m = (np.abs(lx) <= half_l + pad) & (np.abs(ly) <= half_w + pad)
        return rr[m], cc[m]


class _Builder:
    def __init__(self, grid: _Grid):
        self.grid = grid
        self.meshes: list[Mesh] = []
        self.instance_class = [labels.UNLABELED]
        self.instance_kind = ["none"]
        self.footprints = []

    def new_instance(self, cls: int, kind: str) -> int:
        self.instance_class.append(cls)
        self.instance_kind.append(kind)
        return len(self.instance_class) - 1

    def free(self, center, yaw, hl, hw, pad=0.0) -> bool:
        r, c = self.grid.rect_cells(center, yaw, hl, hw, pad)
        return len(r) > 0 and not self.grid.occupied[r, c].any()

    def occupy(self, center, yaw, hl, hw, pad=0.0) -> None:
        r, c = self.grid.rect_cells(center, yaw, hl, hw, pad)
        self.grid.occupied[r, c] = True

    def add(self, mesh: Mesh, inst: int, center, yaw, hl, hw, pad=0.0, footprint=True) -> None:
        self.meshes.append(mesh.with_label(inst))
        self.occupy(center, yaw, hl, hw, pad)
        if footprint:
            self.footprints.append([center[0], center[1], yaw, hl, hw, inst])


def _walk(line: Polyline, rng, spacing, start=None):
    """Arc positions along a line at random spacing."""
    s = rng.uniform(0, spacing[1]) if start is None else start
    out = []
    while s < line.length:
        out.append(s)
        s += rng.uniform(*spacing)
    return np.array(out)


def build_town(net: RoadNetwork, rng: np.random.Generator, style: TownStyle | None = None,
               ego_route: Polyline | None = None) -> StaticWorld:
    style = style or TownStyle()
    grid = _Grid(net, style.margin, CLASS_RESOLUTION)
    b = _Builder(grid)
    d = grid.dist
    class_raster = np.full(grid.shape, labels.TERRAIN, dtype=np.uint8)
    class_raster[d < BUILDING_LINE] = labels.SIDEWALK
    class_raster[d < HALF_WIDTH] = labels.ROAD
    # reserve the driving surface, crosswalks and crossing spots before placing anything
    grid.occupied[d < HALF_WIDTH - PARKING_WIDTH - 0.2] = True
    for cw in net.crosswalks:
        mid = (cw.a + cw.b) / 2
        yaw = np.arctan2(*(cw.b - cw.a)[::-1])
        b.occupy(mid, yaw, np.linalg.norm(cw.b - cw.a) / 2 + 1.2, 3.0)

    lanes = [net.lane_samples(1.0)]
    if ego_route is not None:
        lanes.append(ego_route.resampled(1.0).points)
    lane_tree = cKDTree(np.concatenate(lanes))
    library = shape_library()

    _parked_cars(b, grid, lane_tree, library, rng, style)
    _street_furniture(b, grid, rng, style)
    _buildings(b, grid, rng, style)
    _fences(b, grid, rng, style)
    _inner_trees(b, grid, rng, style)

    walk_loops = []
    for level in WALK_LINES:
        walk_loops += [ln for ln in grid.contours(level, step=0.5, closed_only=True) if ln.length > 30]
    ground = _ground(grid)
    mesh = Mesh.concat([ground] + b.meshes)
    return StaticWorld(
        mesh=mesh,
        instance_class=np.array(b.instance_class, dtype=np.int64),
        instance_kind=b.instance_kind,
        class_raster=class_raster,
        origin=grid.origin.copy(),
        resolution=grid.res,
        footprints=np.array(b.footprints, dtype=np.float64).reshape(-1, 6),
        walk_loops=walk_loops,
    )


def _ground(grid: _Grid) -> Mesh:
    lo = grid.origin - 2000.0
    hi = grid.origin + np.array(grid.shape[::-1]) * grid.res + 2000.0
    v = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32), np.full(2, -1, dtype=np.int64))


def _parked_cars(b: _Builder, grid: _Grid, lane_tree, library, rng, style: TownStyle) -> None:
    cars = shapes_of_kind(library, "car")
    weights = np.array([0.4, 0.3, 0.2, 0.1])[: len(cars)]
    level = HALF_WIDTH - PARKING_WIDTH / 2
    for line in grid.contours(level, step=0.5):
        s = rng.uniform(0, 6.0)
        while s < line.length - 3:
            k = cars[rng.choice(len(cars), p=weights / weights.sum())]
            shape = library[k]
            s_c = s + shape.length / 2
            if s_c > line.length:
                break
            p = line.position(s_c)
            yaw = float(line.heading(s_c))
            if rng.random() < 0.5:
                yaw += np.pi
            c, sn = np.cos(yaw), np.sin(yaw)
            hl, hw = shape.length / 2 + 0.1, shape.width / 2 + 0.1
            corners = p + np.array([[hl, hw], [hl, -hw], [-hl, hw], [-hl, -hw], [hl, 0], [-hl, 0]]) @ np.array(
                [[c, sn], [-sn, c]])
            ok = rng.random() < style.parked_fill
            ok = ok and np.all(grid.lookup(corners) < HALF_WIDTH - 0.05)
            ok = ok and np.all(lane_tree.query(corners)[0] > 1.65)
            ok = ok and b.free(p, yaw, hl, hw)
            if ok:
                inst = b.new_instance(labels.CAR, "parked-car")
                b.add(shape.mesh.transformed(yaw, (p[0], p[1], 0.0)), inst, p, yaw, hl, hw, pad=0.3)
                s += shape.length + rng.uniform(0.8, 3.0)
            else:
                s += rng.uniform(2.0, 6.0)


def _street_furniture(b: _Builder, grid: _Grid, rng, style: TownStyle) -> None:
    for line in grid.contours(FURNITURE, step=0.5):
        for s in _walk(line, rng, style.tree_spacing):
            if rng.random() > style.tree_prob:
                continue
            p = line.position(s)
            r = rng.uniform(0.15, 0.25)
            if not b.free(p, 0.0, 0.5, 0.5):
                continue
            inst = b.new_instance(labels.VEGETATION, "tree")
            h = rng.uniform(2.8, 4.0)
            crown = rng.uniform(1.6, 2.5)
            m = Mesh.concat([
                prism(r, h + 0.5, 8, (p[0], p[1], 0.0)),
                ellipsoid((crown, crown, rng.uniform(1.5, 2.5)), (p[0], p[1], h + 1.4), 6, 10),
            ])
            b.add(m, inst, p, 0.0, r, r, pad=0.8)
        for s in _walk(line, rng, (style.pole_spacing * 0.8, style.pole_spacing * 1.2)):
            p = line.position(s)
            if not b.free(p, 0.0, 0.4, 0.4):
                continue
            inst = b.new_instance(labels.POLE, "pole")
            toward_road = -grid.away(p[None])[0]
            h = rng.uniform(6.5, 8.5)
            arm_c = p + toward_road * 0.9
            m = Mesh.concat([
                prism(0.11, h, 8, (p[0], p[1], 0.0)),
                box((1.8, 0.12, 0.12), (arm_c[0], arm_c[1], h - 0.1), yaw=float(np.arctan2(*toward_road[::-1]))),
            ])
            b.add(m, inst, p, 0.0, 0.11, 0.11, pad=0.5)


def _buildings(b: _Builder, grid: _Grid, rng, style: TownStyle) -> None:
    for line in grid.contours(BUILDING_LINE + 0.3, step=0.5):
        setback = rng.uniform(*style.setback)
        height_bias = rng.uniform(0.0, 1.0)
        s = rng.uniform(0, 5.0)
        while s < line.length - 6:
            w = rng.uniform(*style.building_width)
            depth = rng.uniform(*style.building_depth)
            s_c = s + w / 2
            if s_c > line.length:
                break
            front = line.position(s_c)
            n = grid.away(front[None])[0]
            yaw = float(np.arctan2(n[1], n[0]))  # local x = away from the road
            center = front + n * (setback + depth / 2)
            hl, hw = depth / 2, w / 2
            placed = False
            if rng.random() < style.building_prob:
                r, c = grid.rect_cells(center, yaw, hl + 0.3, hw + 0.3)
                if len(r) and not grid.occupied[r, c].any() and grid.dist[r, c].min() > BUILDING_LINE + 0.1:
                    lo_h, hi_h = style.building_height
                    h = rng.uniform(lo_h, lo_h + (hi_h - lo_h) * (0.4 + 0.6 * height_bias))
                    inst = b.new_instance(labels.BUILDING, "building")
                    parts = [box((depth, w, h), (center[0], center[1], h / 2), yaw=yaw)]
                    if rng.random() < 0.3:  # a lower annex or a roof structure
                        parts.append(box((depth * 0.5, w * 0.4, h * 0.25), (center[0], center[1], h + h * 0.125),
                                         yaw=yaw))
                    b.add(Mesh.concat(parts), inst, center, yaw, hl, hw, pad=0.3)
                    placed = True
            s += w + (rng.uniform(*style.building_gap) if placed else rng.uniform(2.0, 8.0))


def _fences(b: _Builder, grid: _Grid, rng, style: TownStyle) -> None:
    for line in grid.contours(BUILDING_LINE + 0.25, step=0.5):
        s = 0.0
        while s < line.length - 4:
            seg_len = rng.uniform(6.0, 24.0)
            if rng.random() > style.fence_prob:
                s += seg_len
                continue
            wall = rng.random() < 0.35
            height = rng.uniform(1.8, 2.8) if wall else rng.uniform(1.0, 1.8)
            thick = 0.3 if wall else 0.08
            pieces = []
            ss = s
            while ss < min(s + seg_len, line.length - 2.0):
                p0, p1 = line.position(ss), line.position(ss + 2.0)
                mid, d = (p0 + p1) / 2, p1 - p0
                yaw = float(np.arctan2(d[1], d[0]))
                if not b.free(mid, yaw, 1.0, thick / 2 + 0.1):
                    break
                pieces.append((mid, yaw))
                ss += 2.0
            if len(pieces) >= 2:
                inst = b.new_instance(labels.WALL if wall else labels.FENCE, "wall" if wall else "fence")
                for mid, yaw in pieces:
                    b.add(box((2.05, thick, height), (mid[0], mid[1], height / 2), yaw=yaw), inst, mid, yaw, 1.0,
                          thick / 2 + 0.05, pad=0.1)
            s = max(ss, s + 2.0) + rng.uniform(2.0, 10.0)


def _inner_trees(b: _Builder, grid: _Grid, rng, style: TownStyle) -> None:
    area_ha = grid.shape[0] * grid.shape[1] * grid.res**2 / 1e4
    n = int(style.inner_trees_per_hectare * area_ha * 0.3)
    lo = grid.origin
    hi = grid.origin + np.array(grid.shape[::-1]) * grid.res
    pts = rng.uniform(lo, hi, size=(n, 2))
    far = grid.lookup(pts) > BUILDING_LINE + 3.0
    for p in pts[far]:
        if not b.free(p, 0.0, 2.0, 2.0):
            continue
        inst = b.new_instance(labels.VEGETATION, "tree")
        h = rng.uniform(2.5, 5.0)
        crown = rng.uniform(1.5, 3.5)
        m = Mesh.concat([prism(rng.uniform(0.15, 0.35), h + 0.5, 8, (p[0], p[1], 0.0)),
                         ellipsoid((crown, crown, crown * rng.uniform(0.8, 1.3)), (p[0], p[1], h + crown * 0.8), 6, 10)])
        b.add(m, inst, p, 0.0, 0.3, 0.3, pad=1.5)
