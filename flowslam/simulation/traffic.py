"""Moving actors: vehicles, cyclists and pedestrians on the network's tracks, the ego's
convoy and an oncoming stream; a time-stepped traffic simulation and a final collision check.

Kinematics (time step ``DT``): every actor moves along its current track with the
Intelligent Driver Model (desired speed, comfortable acceleration/braking, time
headway, minimum gap) behind its leader on the same track (or the next tracks it
will take), never moving further than the gap to that leader. Desired speeds:
cars 8-15 m/s, trucks 7-12 m/s, cyclists 3-7 m/s (all capped in curves at 2.5 m/s^2
lateral acceleration); pedestrians 0.5-2 m/s.

- Vehicles pick a random connector at each intersection (never a U-turn, never into
  a lane of the ego route). Entering a connector (gated track) needs a grant: no
  conflicting connector in use, room on the exit lane, and the ego group (the ego
  and its convoy) not coming near the connector while the vehicle needs to clear it.
  Vehicles stop at the line otherwise, and before crosswalks in use.
- Walkers follow the sidewalk loops. Crossers shuttle over a crosswalk, starting only
  when no vehicle is on or close to it and the ego group will not reach it before they
  are across.
- Convoy vehicles move with the ego along its route at a fixed arc-length offset
  (e.g. a lead car 17 m ahead): they are dynamic in the world but static relative to
  the sensor, the classic trap for ego-motion from flow. An oncoming stream (procedural
  loops) drives the ego's loops the other way in the oncoming lanes, a fixed headway
  apart. Convoy and stream are scripted: everybody else yields to them (the lanes they
  use are closed to other vehicles; gates and crosswalks wait for them), and an
  oncoming vehicle that would touch the ego or the convoy is left out.
- A vehicle at a dead end (the end of the oncoming lane of a given path) waits there
  and leaves the scene once the ego is out of sensor range.

After the simulation every pair of actor footprints, and each actor against the
ego group and the static obstacles, is checked at every step; an actor that
overlaps anything is removed from the whole sequence (``ActorSet.removed`` counts
them), so actors never interpenetrate each other or the ego vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation import labels
from flowslam.simulation.ego_path import EgoMotion
from flowslam.simulation.meshes import ActorShape, shapes_of_kind
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.roads import RoadNetwork
from flowslam.simulation.town import StaticWorld

DT = 0.1
"""Traffic simulation step (s); actor poses are interpolated linearly in between."""

IDM = {
    # a (m/s^2), b (m/s^2), headway T (s), minimum gap s0 (m)
    "vehicle": (1.5, 2.0, 1.2, 2.5),
    "walker": (1.0, 1.5, 0.6, 0.6),
    "crosser": (1.0, 1.5, 0.6, 0.6),
}


@dataclass
class TrafficSpec:
    """How much traffic (per km of usable track near the ego route)."""

    vehicles_per_km: float = 0.0
    truck_share: float = 0.1
    cyclists_per_km: float = 0.0
    walkers_per_km: float = 0.0
    crossers: float = 0.0
    """Fraction of crosswalks with a crossing pedestrian."""
    convoy: tuple[float, ...] = ()
    """Arc offsets (m, centre to centre) of convoy vehicles on the ego route: + ahead, - behind."""
    oncoming: int = 0
    """Procedural loops: a scripted stream of this many vehicles driving the ego's loops the
    other way (in the oncoming lanes), ``oncoming_headway`` seconds apart."""
    oncoming_headway: float = 2.5
    spawn_radius: float = 160.0
    """Only tracks within this distance of the ego route get vehicles and crossers."""
    walker_radius: float = 60.0
    """Only sidewalk stretches within this distance of the ego route get walkers."""
    target_dynamic: float | None = None
    """Keep only the actors that bring the dynamic points per frame (reference sensor:
    64 x 2048 HDL-64E) closest to this (``selection``); None keeps them all."""


@dataclass
class Actor:
    id: int
    """Instance id (``labels.ACTOR_ID_BASE + k``)."""
    kind: str
    """"vehicle", "walker", "crosser", "convoy" or "oncoming"."""
    shape: int
    track: PoseTrack
    alive: np.ndarray
    """(S,) bool per simulation step."""


@dataclass
class ActorSet:
    actors: list[Actor]
    shapes: list[ActorShape]
    times: np.ndarray
    removed: int = 0
    stats: dict = field(default_factory=dict)

    def alive_at(self, t: float) -> list[int]:
        i = int(np.clip(np.round((t - self.times[0]) / (self.times[1] - self.times[0])), 0, len(self.times) - 1))
        return [k for k, a in enumerate(self.actors) if a.alive[i]]

    def class_of(self, k: int) -> int:
        return self.shapes[self.actors[k].shape].class_id

    def count_by(self, what: str = "shape") -> dict:
        """Actors per shape kind (car, truck, cyclist, pedestrian) or per role (``what="role"``)."""
        out: dict = {}
        for a in self.actors:
            key = self.shapes[a.shape].kind if what == "shape" else a.kind
            out[key] = out.get(key, 0) + 1
        return out


class _Agent:
    __slots__ = ("idx", "kind", "shape", "L", "W", "v0", "track", "s", "v", "plan", "grant", "state",
                 "wait_until", "alive", "req_since", "params", "s_snap", "v_snap", "track_snap", "entered")

    def __init__(self, idx, kind, shape: ActorShape, shape_id, v0, track, s, v):
        self.idx, self.kind, self.shape = idx, kind, shape_id
        self.L, self.W = shape.length, shape.width
        self.v0, self.track, self.s, self.v = v0, track, s, v
        self.plan: list[int] = []
        self.grant = -1
        self.state = "moving"
        self.wait_until = 0.0
        self.alive = True
        self.req_since = None
        self.params = IDM["vehicle" if kind == "vehicle" else kind]
        self.s_snap, self.v_snap, self.track_snap = s, self.v, track
        self.entered = False


def scripted_tracks(ego: EgoMotion, spec: TrafficSpec, times: np.ndarray) -> list[tuple[str, PoseTrack]]:
    """Pose tracks of the convoy and of the oncoming stream (scripted, they yield to nobody)."""
    out = []
    s = ego.s_at(times)
    for d in spec.convoy:
        p, h = ego.route.position(s + d), ego.route.heading(s + d)
        out.append(("convoy", PoseTrack(times, p[:, 0], p[:, 1], h)))
    if spec.oncoming and ego.oncoming_route is not None:
        for i in range(spec.oncoming):
            sr = ego.oncoming_s.at(times - i * spec.oncoming_headway)[0]
            p, h = ego.oncoming_route.position(sr), ego.oncoming_route.heading(sr)
            out.append(("oncoming", PoseTrack(times, p[:, 0], p[:, 1], h)))
    return out


class _EgoGroup:
    """Footprint centres of the ego, its convoy and the oncoming stream at every step."""

    def __init__(self, ego: EgoMotion, times: np.ndarray, scripted: list, radius: float):
        fx, fy, self.ego_yaw = ego.footprint_at(times)
        centers = [np.stack([fx, fy], axis=1)] + [np.stack([tr.x, tr.y], axis=1) for _, tr in scripted]
        self.centers = np.stack(centers, axis=1)  # (S, G, 2)
        self.radius = radius
        self.times = times

    def clear(self, tree: cKDTree, t0: float, t1: float, extra: float) -> bool:
        i0 = max(int(np.floor((t0 - self.times[0]) / DT)), 0)
        i1 = min(int(np.ceil((t1 - self.times[0]) / DT)) + 1, len(self.times))
        if i1 <= i0:
            return True
        pts = self.centers[i0:i1].reshape(-1, 2)
        d, _ = tree.query(pts, distance_upper_bound=self.radius + extra)
        return not np.isfinite(d).any()

    def distance(self, p: np.ndarray, i: int) -> float:
        return float(np.min(np.linalg.norm(self.centers[min(i, len(self.times) - 1)] - p, axis=1)))


def simulate_traffic(net: RoadNetwork, world: StaticWorld, ego: EgoMotion, spec: TrafficSpec,
                     shapes: list[ActorShape], rng: np.random.Generator, t_end: float,
                     despawn_distance: float, ego_size=(4.6, 1.9)) -> ActorSet:
    times = np.arange(0.0, t_end + DT / 2, DT)
    ego_radius = float(np.hypot(*ego_size)) / 2
    cars = shapes_of_kind(shapes, "car")
    scripted = [Actor(-1, kind, int(rng.choice(cars)), tr, np.ones(len(times), dtype=bool))
                for kind, tr in scripted_tracks(ego, spec, times)]
    # an oncoming vehicle that would touch the ego or the convoy (tight corners) is left out
    clash = _scripted_clashes(scripted, shapes, ego, times, ego_size)
    scripted = [a for a, c in zip(scripted, clash) if not c]
    group = _EgoGroup(ego, times, [(a.kind, a.track) for a in scripted], ego_radius)
    tracks = net.tracks
    trees = {}

    def tree_of(k):
        if k not in trees:
            trees[k] = cKDTree(tracks[k].line.points)
        return trees[k]

    for tr in tracks:
        if tr.speed_cap is not None:
            cap = tr.speed_cap
            n = 12  # ~6 m ahead
            padded = np.concatenate([cap, np.full(n, cap[-1])])
            tr.cap_ahead = [float(v) for v in np.lib.stride_tricks.sliding_window_view(padded, n + 1).min(axis=1)]
            tr.cap_entry = float(cap[:20].min())
    agents = _spawn(net, world, ego, spec, shapes, rng)
    n_steps = len(times)
    rec_track = np.full((len(agents), n_steps), -1, dtype=np.int64)
    rec_s = np.zeros((len(agents), n_steps))
    alive = np.zeros((len(agents), n_steps), dtype=bool)
    holders: dict[int, set] = {}
    crosswalk_busy = np.zeros(len(net.crosswalks), dtype=bool)
    cross_of_track = {}
    for cw in net.crosswalks:
        for k in cw.tracks:
            cross_of_track[k] = cw
    road_end = {k: float(np.linalg.norm(cw.b - cw.a)) for cw in net.crosswalks for k in cw.tracks}

    for i, t in enumerate(times):
        # ---- record the state at time t
        for a in agents:
            if a.alive:
                rec_track[a.idx, i], rec_s[a.idx, i], alive[a.idx, i] = a.track, a.s, True
        if i == n_steps - 1:
            break
        # ---- snapshot of the state at t: every decision of this step uses it
        on_track: dict[int, list] = {}
        for a in agents:
            if a.alive:
                a.s_snap, a.v_snap, a.track_snap = a.s, a.v, a.track
                on_track.setdefault(a.track, []).append(a)
        rank = {}
        for lst in on_track.values():
            lst.sort(key=lambda a: (a.s_snap, a.idx))
            for r, a in enumerate(lst):
                rank[a.idx] = r
        crosswalk_busy[:] = False
        for a in agents:
            if a.alive and a.kind == "crosser" and a.state == "moving" and a.s_snap < road_end[a.track] + 0.5:
                crosswalk_busy[cross_of_track[a.track].id] = True
        # ---- plans
        for a in agents:
            if a.alive and a.kind == "vehicle":
                _extend_plan(a, tracks, rng)
        # ---- gates: release, then grant in order of waiting
        for g, hs in list(holders.items()):
            for a in list(hs):
                done = a.entered and a.track != g and (a.track not in tracks[g].next or a.s - a.L / 2 > 0.5)
                if not a.alive or a.grant != g or done:
                    hs.discard(a)
                    if a.grant == g:
                        a.grant = -1
        waiting = []
        for a in agents:
            if a.alive and a.kind == "vehicle" and a.plan and tracks[a.plan[0]].gated and a.grant != a.plan[0]:
                # only the first vehicle of a lane asks, once it is close to the stop line
                dist_end = tracks[a.track].line.length - a.s_snap - a.L / 2
                first = rank[a.idx] == len(on_track[a.track_snap]) - 1
                if first and dist_end < max(a.v_snap * a.v_snap / 3.0 + 5.0, 8.0):
                    if a.req_since is None:
                        a.req_since = t
                    waiting.append(a)
        waiting.sort(key=lambda a: (a.req_since, a.idx))
        for a in waiting:
            g = a.plan[0]
            if any(holders.get(c) for c in tracks[g].conflicts):
                continue
            ext = a.plan[1] if len(a.plan) > 1 else None
            if ext is not None and not _exit_room(a, g, ext, on_track, holders, tracks):
                continue
            dist = tracks[a.track].line.length - a.s + tracks[g].line.length + a.L + 5.0
            horizon = max(np.sqrt(2 * dist / a.params[0]), dist / max(a.v, 1.0)) + 2.5
            if not group.clear(tree_of(g), t, t + horizon, 1.6):
                continue
            holders.setdefault(g, set()).add(a)
            a.grant, a.req_since, a.entered = g, None, False
        # ---- crossers: start crossing?
        for a in agents:
            if a.alive and a.kind == "crosser" and a.state == "waiting" and t >= a.wait_until:
                cw = cross_of_track[a.track]
                duration = (tracks[a.track].line.length + 1.0) / a.v0 + 2.0
                if _crosswalk_free(cw, on_track, tracks) and group.clear(_cw_tree(cw), t, t + duration, 1.5):
                    a.state = "moving"
                    crosswalk_busy[cw.id] = True
        # ---- IDM for everybody
        for a in agents:
            if not a.alive:
                continue
            if a.kind == "crosser" and a.state == "waiting":
                a.v = 0.0
                continue
            gap, v_lead = _leader(a, rank[a.idx], on_track, tracks, crosswalk_busy)
            v_des = _desired_speed(a, tracks)
            acc = _idm(a, gap, v_lead, v_des)
            v_new = max(0.0, a.v + acc * DT)
            free_step = 0.5 * (a.v + v_new) * DT
            step = min(free_step, max(gap - 0.05, 0.0))
            a.v = v_new if step >= free_step else min(v_new, step / DT)
            a.s += step
            _advance(a, tracks, rng, t + DT, road_end)
            if a.track == a.grant:
                a.entered = True
            if a.kind == "vehicle" and a.alive and not a.plan:
                # dead end: leave the scene once out of the ego's sight
                end_pos = tracks[a.track].line.points[-1]
                if tracks[a.track].line.length - a.s < a.L and group.distance(end_pos, i) > despawn_distance:
                    a.alive = False
    actors = _to_actors(agents, rec_track, rec_s, alive, times, tracks, shapes)
    actors += scripted
    report: list = []
    removed = validate(actors, shapes, group, world, ego_size, report)
    for k, a in enumerate(actors):
        a.id = labels.ACTOR_ID_BASE + k
    collisions: dict = {}
    for pair in report:
        key = "-".join(pair)
        collisions[key] = collisions.get(key, 0) + 1
    return ActorSet(actors, shapes, times, removed=removed, stats={"collisions": collisions})


# ------------------------------------------------------------------ spawning
def _near_route(points: np.ndarray, route_tree: cKDTree, radius: float) -> np.ndarray:
    d, _ = route_tree.query(points, distance_upper_bound=radius)
    return np.isfinite(d)


def _spawn(net, world, ego, spec: TrafficSpec, shapes, rng) -> list[_Agent]:
    sampled = ego.route.resampled(2.0)
    # only the part of the route that this sequence drives (plus a margin)
    s_lo = ego.s_at(ego.frame_times[0]) - 50.0
    s_hi = ego.s_at(ego.frame_times[-1]) + 150.0
    keep = (sampled.s >= s_lo) & (sampled.s <= s_hi)
    route_tree = cKDTree(sampled.points[keep] if keep.any() else sampled.points)
    agents: list[_Agent] = []
    occupied: dict[int, list] = {}

    def place(kind, shape_id, track, s, v0):
        shape = shapes[shape_id]
        lst = occupied.setdefault(track, [])
        clearance = (shape.length + 6.0) if kind == "vehicle" else 1.2
        if any(abs(s - s2) < clearance / 2 + l2 / 2 for s2, l2 in lst):
            return None
        lst.append((s, clearance))
        a = _Agent(len(agents), kind, shape, shape_id, v0, track, s, v0 * rng.uniform(0.4, 1.0))
        agents.append(a)
        return a

    # vehicles and cyclists on plain lanes near the route (not on the ego's lanes)
    lanes = [t for t in net.tracks if t.kind == "lane" and not t.ego and not t.gated]
    usable = []
    for t in lanes:
        pts = t.line.points
        near = _near_route(pts, route_tree, spec.spawn_radius)
        if near.any():
            usable.append((t, t.line.s[near]))
    total_km = sum(len(s) * 0.5 for _, s in usable) / 1000.0
    cars, trucks, cyclists = (shapes_of_kind(shapes, k) for k in ("car", "truck", "cyclist"))
    for count, kind_pool in ((spec.vehicles_per_km * total_km, "motor"), (spec.cyclists_per_km * total_km, "cyclist")):
        n = rng.poisson(count) if count > 0 else 0
        for _ in range(n * 3):
            if n <= 0 or not usable:
                break
            t, s_ok = usable[rng.integers(len(usable))]
            s = float(rng.choice(s_ok))
            if kind_pool == "cyclist":
                shape_id, v0 = int(rng.choice(cyclists)), rng.uniform(3.0, 7.0)
            elif rng.random() < spec.truck_share:
                shape_id, v0 = int(rng.choice(trucks)), rng.uniform(7.0, 12.0)
            else:
                shape_id, v0 = int(rng.choice(cars)), rng.uniform(8.0, 15.0)
            half = shapes[shape_id].length / 2
            if s < half + 1 or s > t.line.length - half - 1:
                continue
            if place("vehicle", shape_id, t.id, s, v0) is not None:
                n -= 1
    # walkers on sidewalk loops
    peds = shapes_of_kind(shapes, "pedestrian")
    loops = []
    for line in world.walk_loops:
        near = _near_route(line.points, route_tree, spec.walker_radius)
        if near.any():
            k = net.add_track("walk", line).id
            net.tracks[k].next = [k]
            loops.append((k, line.s[near]))
    total_km = sum(len(s) * 0.5 for _, s in loops) / 1000.0
    n = rng.poisson(spec.walkers_per_km * total_km) if spec.walkers_per_km > 0 else 0
    for _ in range(n * 3):
        if n <= 0 or not loops:
            break
        k, s_ok = loops[rng.integers(len(loops))]
        if place("walker", int(rng.choice(peds)), k, float(rng.choice(s_ok)), rng.uniform(0.6, 1.8)) is not None:
            n -= 1
    # crossers
    for cw in net.crosswalks:
        if rng.random() < spec.crossers and _near_route(cw.samples[:1], route_tree, spec.spawn_radius).any():
            k = cw.tracks[rng.integers(2)]
            a = place("crosser", int(rng.choice(peds)), k, 0.0, rng.uniform(1.0, 1.8))
            if a is not None:
                a.state, a.v, a.wait_until = "waiting", 0.0, rng.uniform(0.0, 6.0)
    return agents


# ------------------------------------------------------------------ per-step helpers
def _extend_plan(a: _Agent, tracks, rng) -> None:
    while len(a.plan) < 3:
        last = a.plan[-1] if a.plan else a.track
        options = tracks[last].next
        if tracks[last].kind == "lane":
            # never into a lane of the ego route
            options = [c for c in options if not any(tracks[n].ego for n in tracks[c].next)]
        if not options:
            return
        a.plan.append(int(options[rng.integers(len(options))]))


def _exit_room(a, g, ext, on_track, holders, tracks) -> bool:
    others = on_track.get(ext, [])
    free = min((o.s_snap - o.L / 2 for o in others), default=tracks[ext].line.length)
    for o in holders.get(g, ()):
        if o is not a and o.track != ext:
            free -= o.L + 3.0
    return free >= a.L + 3.0


def _cw_tree(cw) -> cKDTree:
    if not hasattr(cw, "_tree"):
        cw._tree = cKDTree(cw.samples)
    return cw._tree


def _crosswalk_free(cw, on_track, tracks) -> bool:
    for k, s_cross in cw.lanes:
        for o in on_track.get(k, []):
            before = o.v_snap * o.v_snap / (2 * 2.5) + o.L / 2 + 8.0
            if s_cross - before <= o.s_snap <= s_cross + 3.0 + o.L / 2:
                return False
    return True


def _leader(a: _Agent, k: int, on_track, tracks, busy) -> tuple[float, float]:
    """Gap (m, front to rear) to whatever ``a`` must stay behind, and its speed (snapshot values):
    the next agent on its track or the tracks it will take, a stop line before a crosswalk
    in use, or the stop line of a gate it has no grant for."""
    lst = on_track.get(a.track_snap, [])
    cur = tracks[a.track_snap]
    if cur.kind == "walk":
        if k + 1 < len(lst):
            o = lst[k + 1]
            return o.s_snap - a.s_snap - (o.L + a.L) / 2, o.v_snap
        if len(lst) > 1:
            o = lst[0]
            return o.s_snap + cur.line.length - a.s_snap - (o.L + a.L) / 2, o.v_snap
        return math.inf, 0.0
    best_gap, best_v = math.inf, 0.0
    dist = -a.s_snap  # arc of the current track's start relative to the agent
    for j, k2 in enumerate([a.track_snap] + (a.plan if a.kind == "vehicle" else [])):
        tr = tracks[k2]
        if j > 0 and tr.gated and a.grant != k2:
            best_gap = min(best_gap, dist - a.L / 2 - 0.5)  # stop line at the end of the previous track
            break
        if a.kind == "vehicle":
            for s_stop, cid in tr.crosswalks:
                if busy[cid] and (j > 0 or a.s_snap + a.L / 2 <= s_stop + 0.2):
                    best_gap = min(best_gap, dist + s_stop - a.L / 2)
        lst2 = on_track.get(k2, [])
        o = lst[k + 1] if (j == 0 and k + 1 < len(lst)) else (lst2[0] if j > 0 and lst2 else None)
        if o is not None:
            gap = dist + o.s_snap - (o.L + a.L) / 2
            if gap < best_gap:
                best_gap, best_v = gap, o.v_snap
            break
        dist += tr.line.length
        if dist > 120.0:
            break
    else:
        if a.kind == "vehicle":
            best_gap = min(best_gap, dist - a.L / 2 - 0.5)  # end of the known route: stop there
    return best_gap, best_v


def _desired_speed(a: _Agent, tracks) -> float:
    cur = tracks[a.track_snap]
    if cur.speed_cap is None:
        return a.v0
    ahead = cur.cap_ahead
    idx = min(int(a.s_snap / max(cur.line.length, 1e-9) * (len(ahead) - 1)), len(ahead) - 1)
    v = min(a.v0, ahead[idx])
    if a.plan:
        nxt = tracks[a.plan[0]]
        if nxt.speed_cap is not None:
            v = min(v, math.sqrt(nxt.cap_entry**2 + 3.0 * max(cur.line.length - a.s_snap, 0.0)))
    return max(v, 0.5)


def _idm(a: _Agent, gap: float, v_lead: float, v_des: float) -> float:
    acc_max, b, T, s0 = a.params
    v = a.v_snap
    free = acc_max * (1.0 - (v / v_des) ** 4)
    if gap == math.inf:
        return max(free, -9.0)
    gap = max(gap, 0.01)
    s_star = s0 + max(0.0, v * T + v * (v - v_lead) / (2 * math.sqrt(acc_max * b)))
    return min(max(free - acc_max * (s_star / gap) ** 2, -9.0), acc_max)


def _advance(a: _Agent, tracks, rng, t_next: float, road_end) -> None:
    while a.alive:
        cur = tracks[a.track]
        L = cur.line.length
        if a.s <= L:
            return
        if cur.kind == "walk":
            a.s -= L
            continue
        if a.kind == "crosser":
            a.track = cur.next[0]
            a.s = 0.0
            a.state, a.v, a.wait_until = "waiting", 0.0, t_next + rng.uniform(2.0, 12.0)
            return
        if not a.plan:
            a.s, a.v = L, 0.0
            return
        a.s -= L
        a.track = a.plan.pop(0)


# ------------------------------------------------------------------ results
def _to_actors(agents, rec_track, rec_s, alive, times, tracks, shapes) -> list[Actor]:
    x = np.zeros(rec_s.shape)
    y = np.zeros(rec_s.shape)
    yaw = np.zeros(rec_s.shape)
    for k in np.unique(rec_track[rec_track >= 0]):
        m = rec_track == k
        line = tracks[k].line
        p = line.position(rec_s[m])
        x[m], y[m] = p[:, 0], p[:, 1]
        yaw[m] = line.heading(rec_s[m])
    out = []
    for a in agents:
        al = alive[a.idx]
        if not al.any():
            continue
        # hold the pose outside the alive span so the track stays continuous
        first, last = np.flatnonzero(al)[[0, -1]]
        xs, ys, hs = x[a.idx].copy(), y[a.idx].copy(), yaw[a.idx].copy()
        xs[:first], ys[:first], hs[:first] = xs[first], ys[first], hs[first]
        xs[last + 1:], ys[last + 1:], hs[last + 1:] = xs[last], ys[last], hs[last]
        hs = _unwrap_heading(hs)
        out.append(Actor(-1, a.kind, a.shape, PoseTrack(times, xs, ys, hs), al.copy()))
    return out


def _unwrap_heading(h: np.ndarray) -> np.ndarray:
    return np.unwrap(h)


def _scripted_clashes(scripted: list[Actor], shapes, ego: EgoMotion, times, ego_size) -> np.ndarray:
    """For each scripted actor: does it ever overlap the ego or a convoy vehicle?"""
    fx, fy, fyaw = ego.footprint_at(times)
    ref = [(fx, fy, fyaw, ego_size[0] / 2, ego_size[1] / 2)]
    ref += [(a.track.x, a.track.y, a.track.yaw, shapes[a.shape].length / 2, shapes[a.shape].width / 2)
            for a in scripted if a.kind == "convoy"]
    out = np.zeros(len(scripted), dtype=bool)
    n = len(times)
    for j, a in enumerate(scripted):
        if a.kind == "convoy":
            continue
        hl, hw = shapes[a.shape].length / 2, shapes[a.shape].width / 2
        A = _corners(a.track.x, a.track.y, a.track.yaw, np.full(n, hl), np.full(n, hw))
        for rx, ry, ryaw, rhl, rhw in ref:
            near = np.hypot(a.track.x - rx, a.track.y - ry) < np.hypot(hl, hw) + np.hypot(rhl, rhw)
            if near.any():
                B = _corners(rx[near], ry[near], ryaw[near], np.full(near.sum(), rhl), np.full(near.sum(), rhw))
                if rectangles_overlap(A[near], B).any():
                    out[j] = True
                    break
    return out


# ------------------------------------------------------------------ collision check
def _corners(cx, cy, yaw, hl, hw) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=np.float64)
    lx = loc[None, :, 0] * hl[:, None]
    ly = loc[None, :, 1] * hw[:, None]
    return np.stack([cx[:, None] + c[:, None] * lx - s[:, None] * ly,
                     cy[:, None] + s[:, None] * lx + c[:, None] * ly], axis=-1)


def rectangles_overlap(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Separating-axis test for pairs of convex quads A[k], B[k] (each (K,4,2))."""
    hit = np.ones(len(A), dtype=bool)
    for P in (A, B):
        edges = np.roll(P, -1, axis=1) - P
        normals = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)  # (K,4,2)
        for e in range(4):
            n = normals[:, e, None, :]
            pa = (A * n).sum(-1)
            pb = (B * n).sum(-1)
            sep = (pa.max(1) < pb.min(1)) | (pb.max(1) < pa.min(1))
            hit &= ~sep
    return hit


def validate(actors: list[Actor], shapes, group: _EgoGroup, world: StaticWorld | None,
             ego_size=(4.6, 1.9), report: list | None = None) -> int:
    """Remove (in place) every non-convoy actor that ever overlaps another actor, the ego
    or a static obstacle; returns how many were removed."""
    if not actors:
        return 0
    n_steps = len(group.times)
    X = np.stack([a.track.x for a in actors])
    Y = np.stack([a.track.y for a in actors])
    H = np.stack([a.track.yaw for a in actors])
    alive = np.stack([a.alive for a in actors])
    HL = np.array([shapes[a.shape].length / 2 for a in actors])
    HW = np.array([shapes[a.shape].width / 2 for a in actors])
    R = np.hypot(HL, HW)
    convoy = np.array([a.kind in ("convoy", "oncoming") for a in actors])
    bad = np.zeros(len(actors), dtype=bool)

    def flag(ka, kb=None, what="actor"):
        # of an overlapping pair, drop the non-convoy one with the larger index
        if report is not None:
            for j, k in enumerate(ka):
                other = actors[kb[j]].kind if kb is not None else what
                report.append((actors[k].kind, other))
        if kb is None:
            bad[ka[~convoy[ka]]] = True
            return
        victim = np.where(convoy[ka], kb, np.where(convoy[kb], ka, np.maximum(ka, kb)))
        bad[victim[~convoy[victim]]] = True

    # actor vs actor, step by step
    for i in range(n_steps):
        idx = np.flatnonzero(alive[:, i])
        if len(idx) < 2:
            continue
        c = np.stack([X[idx, i], Y[idx, i]], 1)
        pairs = cKDTree(c).query_pairs(2 * R[idx].max() + 0.1, output_type="ndarray")
        if len(pairs) == 0:
            continue
        p, q = idx[pairs[:, 0]], idx[pairs[:, 1]]
        close = np.hypot(X[p, i] - X[q, i], Y[p, i] - Y[q, i]) < R[p] + R[q]
        p, q = p[close], q[close]
        if len(p):
            hit = rectangles_overlap(_corners(X[p, i], Y[p, i], H[p, i], HL[p], HW[p]),
                                     _corners(X[q, i], Y[q, i], H[q, i], HL[q], HW[q]))
            flag(p[hit], q[hit])
    # actor vs ego, all steps at once
    ec = group.centers[:, 0]
    ehl, ehw = ego_size[0] / 2, ego_size[1] / 2
    d = np.hypot(X - ec[None, :, 0], Y - ec[None, :, 1])
    ka, st = np.nonzero(alive & (d < R[:, None] + np.hypot(ehl, ehw) + 0.1))
    if len(ka):
        n = len(ka)
        ego_c = _corners(ec[st, 0], ec[st, 1], group.ego_yaw[st], np.full(n, ehl), np.full(n, ehw))
        hit = rectangles_overlap(_corners(X[ka, st], Y[ka, st], H[ka, st], HL[ka], HW[ka]), ego_c)
        flag(np.unique(ka[hit]), what="ego")
    # actor vs static obstacles, all steps at once
    if world is not None and len(world.footprints):
        f = world.footprints
        fr = np.hypot(f[:, 3], f[:, 4])
        ka, st = np.nonzero(alive)
        pts = np.stack([X[ka, st], Y[ka, st]], 1)
        sd = cKDTree(f[:, :2]).sparse_distance_matrix(cKDTree(pts), R.max() + fr.max(), output_type="ndarray")
        if len(sd):
            j, k = sd["i"], sd["j"]
            close = sd["v"] < fr[j] + R[ka[k]]
            j, k = j[close], k[close]
            if len(j):
                a_k, s_k = ka[k], st[k]
                hit = rectangles_overlap(_corners(X[a_k, s_k], Y[a_k, s_k], H[a_k, s_k], HL[a_k], HW[a_k]),
                                         _corners(f[j, 0], f[j, 1], f[j, 2], f[j, 3], f[j, 4]))
                flag(np.unique(a_k[hit]), what="static")
                if report is not None:
                    report.extend(("static-kind", world.instance_kind[int(f[jj, 5])]) for jj in np.unique(j[hit]))
    for k in sorted(np.flatnonzero(bad), reverse=True):
        del actors[k]
    return int(bad.sum())
