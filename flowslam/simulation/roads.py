"""Road networks: centrelines, driving lanes, intersection connectors, crosswalks.

Cross-section of every road (right-hand traffic, metres from the centreline):
one lane per direction (``LANE_WIDTH`` 3.5, lane centres at +-1.75), a parking strip
on each side (to ``HALF_WIDTH`` = 5.7, the curb), a sidewalk (to
``HALF_WIDTH + SIDEWALK_WIDTH`` = 9.2). Buildings stand behind the sidewalk.

Everything that moves does so on *tracks* (directed polylines): ``lane`` and
``connector`` tracks for vehicles and cyclists (connectors cross intersections and
are *gated*: a vehicle needs a grant to enter one), ``walk`` loops on sidewalks and
``cross`` tracks over crosswalks for pedestrians. The ego vehicle does not use
tracks; it has its own route (``ego_path``) and the others yield to it.

Two builders: ``grid_network`` (procedural town: a jittered grid of intersections
with some curved roads) and ``path_network`` (a town grown around a given ego path,
e.g. the real KITTI-00 trajectory: one road along the path, traffic in the
oncoming lane).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation.paths import Polyline, quad_bezier

LANE_WIDTH = 3.5
LANE_OFFSET = LANE_WIDTH / 2
PARKING_WIDTH = 2.2
HALF_WIDTH = LANE_WIDTH + PARKING_WIDTH
SIDEWALK_WIDTH = 3.5
CURB_SPOT = HALF_WIDTH + 0.5
"""Where crossing pedestrians wait: 0.5 m behind the curb, before the tree/pole strip."""
FURNITURE = HALF_WIDTH + 0.8
"""Trees and poles stand on this line."""
WALK_LINES = (HALF_WIDTH + 1.7, HALF_WIDTH + 2.7)
"""Sidewalk walking lines: one per walking direction."""
BUILDING_LINE = HALF_WIDTH + SIDEWALK_WIDTH
CONFLICT_DISTANCE = 3.4
"""Two vehicle tracks closer than this (centre lines, m) cannot be used at once."""


@dataclass
class Track:
    id: int
    kind: str
    """"lane", "connector", "walk", "cross"."""
    line: Polyline
    next: list[int] = field(default_factory=list)
    gated: bool = False
    conflicts: set = field(default_factory=set)
    crosswalks: list = field(default_factory=list)
    """(s_stop, crosswalk id) pairs: vehicles stop before ``s_stop`` while it is in use."""
    speed_cap: np.ndarray | None = None
    """Per-vertex speed limit from curvature (m/s), vehicles only."""
    ego: bool = False
    """A lane of the ego route: no other vehicle is routed onto it."""
    cap_ahead: list | None = None
    """Per vertex: the lowest speed cap of the next ~6 m (set by the traffic simulation)."""
    cap_entry: float = 0.0


@dataclass
class Crosswalk:
    id: int
    a: np.ndarray
    b: np.ndarray
    tracks: tuple[int, int]
    lanes: list = field(default_factory=list)
    """(track id, s of the crossing on that track)."""
    samples: np.ndarray | None = None
    """Points along the crossing (for the ego-occupancy test)."""


@dataclass
class RoadNetwork:
    centerlines: list[Polyline]
    nodes: np.ndarray
    tracks: list[Track] = field(default_factory=list)
    crosswalks: list[Crosswalk] = field(default_factory=list)
    node_of_edge: list[tuple[int, int]] = field(default_factory=list)
    lane_ids: dict = field(default_factory=dict)
    """(edge, direction) -> lane track id, direction +1 = from edge's u to v."""
    kind: str = "grid"

    def add_track(self, kind: str, line: Polyline, **kw) -> Track:
        t = Track(len(self.tracks), kind, line, **kw)
        self.tracks.append(t)
        return t

    def vehicle_tracks(self) -> list[Track]:
        return [t for t in self.tracks if t.kind in ("lane", "connector")]

    def lane_samples(self, step: float = 1.0) -> np.ndarray:
        """Points along every vehicle track (for clearance tests)."""
        pts = [t.line.resampled(step).points for t in self.vehicle_tracks()]
        return np.concatenate(pts) if pts else np.zeros((0, 2))

    def centerline_samples(self, step: float = 1.0) -> np.ndarray:
        return np.concatenate([c.resampled(step).points for c in self.centerlines])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        pts = self.centerline_samples(5.0)
        return pts.min(axis=0), pts.max(axis=0)


# ------------------------------------------------------------------ helpers
def _trim(line: Polyline, start: float, end: float, step: float = 0.5) -> Polyline | None:
    if line.length - start - end < 2.0:
        return None
    return line.sub(start, line.length - end, step)


def _control_point(p0, h0, p2, h2):
    d0 = np.array([np.cos(h0), np.sin(h0)])
    d2 = np.array([np.cos(h2), np.sin(h2)])
    A = np.column_stack([d0, d2])  # p0 + a d0 = p2 - b d2, both a, b > 0
    if abs(np.linalg.det(A)) < 1e-3:
        return (p0 + p2) / 2
    a, b = np.linalg.solve(A, p2 - p0)
    if a <= 0 or b <= 0:
        return (p0 + p2) / 2
    return p0 + a * d0


def speed_caps(line: Polyline, lateral_accel: float = 2.5, vmax: float = 20.0) -> np.ndarray:
    k = line.curvature()
    # smooth the curvature a little (vertex spacing is ~0.5 m)
    if len(k) > 5:
        k = np.convolve(np.pad(k, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    return np.minimum(vmax, np.sqrt(lateral_accel / np.maximum(k, 1e-6)))


def _finish_conflicts(net: RoadNetwork, gated: list[Track]) -> None:
    """Gated tracks conflict when their centre lines come within CONFLICT_DISTANCE."""
    samples = [t.line.resampled(0.5).points for t in gated]
    trees = [cKDTree(s) for s in samples]
    for i in range(len(gated)):
        for j in range(i + 1, len(gated)):
            lo = np.maximum(samples[i].min(0), samples[j].min(0)) - CONFLICT_DISTANCE
            hi = np.minimum(samples[i].max(0), samples[j].max(0)) + CONFLICT_DISTANCE
            if np.any(lo > hi):
                continue
            d, _ = trees[j].query(samples[i], distance_upper_bound=CONFLICT_DISTANCE)
            if np.isfinite(d).any():
                gated[i].conflicts.add(gated[j].id)
                gated[j].conflicts.add(gated[i].id)


# ------------------------------------------------------------------ procedural grid
def grid_network(rng: np.random.Generator, nx: int = 5, ny: int = 5, block=(70.0, 110.0),
                 jitter: float = 6.0, curve_prob: float = 0.3, crosswalk_prob: float = 0.5) -> RoadNetwork:
    """A jittered ``nx`` x ``ny`` grid of intersections joined by (sometimes curved) roads."""
    gx = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, size=nx - 1))])
    gy = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, size=ny - 1))])
    gx -= gx.mean()
    gy -= gy.mean()
    nodes = np.array([[x, y] for j, y in enumerate(gy) for i, x in enumerate(gx)])
    nodes += rng.uniform(-jitter, jitter, size=nodes.shape)
    idx = lambda i, j: j * nx + i  # noqa: E731
    edges = [(idx(i, j), idx(i + 1, j)) for j in range(ny) for i in range(nx - 1)]
    edges += [(idx(i, j), idx(i, j + 1)) for j in range(ny - 1) for i in range(nx)]
    centerlines = []
    for u, v in edges:
        p0, p2 = nodes[u], nodes[v]
        length = np.linalg.norm(p2 - p0)
        if rng.random() < curve_prob:
            normal = np.array([-(p2 - p0)[1], (p2 - p0)[0]]) / length
            ctrl = (p0 + p2) / 2 + normal * rng.uniform(0.08, 0.16) * length * rng.choice([-1, 1])
            pts = quad_bezier(p0, ctrl, p2, step=1.0)
        else:
            pts = np.linspace(p0, p2, max(int(length), 2) + 1)
        centerlines.append(Polyline(pts))
    net = RoadNetwork(centerlines=centerlines, nodes=nodes, node_of_edge=edges, kind="grid")

    trim = HALF_WIDTH + 3.5
    # lanes
    incoming: dict[int, list[int]] = {n: [] for n in range(len(nodes))}
    outgoing: dict[int, list[int]] = {n: [] for n in range(len(nodes))}
    lane_edge = {}
    for e, (u, v) in enumerate(edges):
        c = centerlines[e]
        for direction, line, start, end in ((1, c, u, v), (-1, c.reversed(), v, u)):
            lane = _trim(line.offset(-LANE_OFFSET), trim, trim)
            if lane is None:
                continue
            t = net.add_track("lane", lane)
            net.lane_ids[(e, direction)] = t.id
            lane_edge[t.id] = (e, start, end)
            outgoing[start].append(t.id)
            incoming[end].append(t.id)
    # connectors
    gated = []
    for n in range(len(nodes)):
        for tin in incoming[n]:
            e_in = lane_edge[tin][0]
            a = net.tracks[tin].line
            for tout in outgoing[n]:
                if lane_edge[tout][0] == e_in:
                    continue  # no U-turns
                b = net.tracks[tout].line
                p0, p2 = a.points[-1], b.points[0]
                ctrl = _control_point(p0, a.vertex_heading[-1], p2, b.vertex_heading[0])
                con = net.add_track("connector", Polyline(quad_bezier(p0, ctrl, p2, step=0.5)),
                                    next=[tout], gated=True)
                net.tracks[tin].next.append(con.id)
                gated.append(con)
    _finish_conflicts(net, gated)
    # crosswalks, mid-block
    for e, (u, v) in enumerate(edges):
        c = centerlines[e]
        if c.length < 2 * trim + 40 or rng.random() > crosswalk_prob:
            continue
        s = rng.uniform(0.35, 0.65) * c.length
        _add_crosswalk(net, c, s)
    for t in net.vehicle_tracks():
        t.speed_cap = speed_caps(t.line)
    return net


def _add_crosswalk(net: RoadNetwork, centerline: Polyline, s: float, vehicle_tracks=None) -> Crosswalk:
    p = centerline.position(s)
    h = centerline.heading(s)
    tangent = np.array([np.cos(h), np.sin(h)])
    normal = np.array([-np.sin(h), np.cos(h)])
    a, b = p + CURB_SPOT * normal, p - CURB_SPOT * normal
    cid = len(net.crosswalks)
    # one crossing pedestrian shuttles: a -> b on one side of the crosswalk, a side step at b,
    # b -> a on the other side, a side step at a (the end of each track is the start of the other)
    t1 = net.add_track("cross", Polyline(np.concatenate([np.linspace(a + 0.6 * tangent, b + 0.6 * tangent, 30),
                                                         [b - 0.6 * tangent]])))
    t2 = net.add_track("cross", Polyline(np.concatenate([np.linspace(b - 0.6 * tangent, a - 0.6 * tangent, 30),
                                                         [a + 0.6 * tangent]])))
    t1.next, t2.next = [t2.id], [t1.id]
    cw = Crosswalk(cid, a, b, (t1.id, t2.id), samples=np.linspace(a, b, 25))
    net.crosswalks.append(cw)
    # vehicle tracks crossing it: stop line 3 m before the crossing centre
    candidates = vehicle_tracks if vehicle_tracks is not None else [t for t in net.tracks if t.kind == "lane"]
    seg = np.linspace(a, b, 40)
    for t in candidates:
        pts = t.line.points
        lo, hi = seg.min(0) - 3, seg.max(0) + 3
        near = np.all((pts >= lo) & (pts <= hi), axis=1)
        if not near.any():
            continue
        d = np.linalg.norm(pts[near][:, None, :] - seg[None], axis=2).min(axis=1)
        k = np.argmin(d)
        if d[k] < 1.0:
            s_cross = t.line.s[np.flatnonzero(near)[k]]
            cw.lanes.append((t.id, float(s_cross)))
            t.crosswalks.append((float(s_cross) - 3.0, cid))
    return cw


# ------------------------------------------------------------------ around a given path
def path_network(ego_line: Polyline, rng: np.random.Generator, crosswalk_every: float = 150.0) -> RoadNetwork:
    """One road along ``ego_line`` (the ego drives in its right lane); other vehicles use
    the oncoming lane. Stretches of the oncoming lane that the ego (elsewhere on its
    path) or the oncoming lane itself crosses or shares are gated tracks."""
    E = ego_line.resampled(0.5)
    center = E.offset(LANE_OFFSET)
    net = RoadNetwork(centerlines=[center], nodes=np.zeros((0, 2)), kind="path")
    O = E.offset(LANE_WIDTH).reversed()
    pts = O.points
    ego_tree = cKDTree(E.points)
    d_ego, _ = ego_tree.query(pts, distance_upper_bound=CONFLICT_DISTANCE + 0.2)
    unsafe = np.isfinite(d_ego)
    own = cKDTree(pts)
    for i, j in own.query_pairs(CONFLICT_DISTANCE):
        if abs(O.s[i] - O.s[j]) > 12.0:
            unsafe[i] = unsafe[j] = True
    # dilate by ~6 m so a vehicle waiting before a gated piece is clear of it
    k = int(6.0 / 0.5)
    unsafe = np.convolve(unsafe.astype(int), np.ones(2 * k + 1, dtype=int), mode="same") > 0
    breaks = np.flatnonzero(np.diff(unsafe.astype(int))) + 1
    bounds = np.concatenate([[0], breaks, [len(pts) - 1]])
    pieces = []
    gated = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 1:
            continue
        line = Polyline(pts[a:b + 1])
        t = net.add_track("connector" if unsafe[a] else "lane", line, gated=bool(unsafe[a]))
        pieces.append(t)
        if t.gated:
            gated.append(t)
    for t0, t1 in zip(pieces[:-1], pieces[1:]):
        t0.next = [t1.id]
    _finish_conflicts(net, gated)
    for t in net.vehicle_tracks():
        t.speed_cap = speed_caps(t.line)
    # crosswalks where the road is a plain two-way street (no other part of it nearby)
    c_tree = cKDTree(center.points)
    s_all = np.arange(40.0, center.length - 40.0, crosswalk_every)
    for s in s_all + rng.uniform(-30, 30, size=len(s_all)):
        p = center.position(s)
        h = center.heading(s)
        normal = np.array([-np.sin(h), np.cos(h)])
        probe = p + np.linspace(-BUILDING_LINE - 2, BUILDING_LINE + 2, 25)[:, None] * normal
        idx = c_tree.query_ball_point(probe, BUILDING_LINE + 4)
        arcs = np.concatenate([center.s[np.asarray(i, dtype=int)] for i in idx if len(i)] or [np.zeros(0)])
        if len(arcs) and np.all(np.abs(arcs - s) < 25.0):
            _add_crosswalk(net, center, s, vehicle_tracks=net.vehicle_tracks())
    return net
