"""Stepping the simulated actors over time: ``Agent`` (the mutable state of one actor),
``run_steps`` (the time-stepped simulation: right of way at gates and crosswalks, then
car-following for everybody), the per-step kinematics helpers, and ``agents_to_actors``
(the recorded arc positions turned into pose tracks).

Every agent moves along a track of the ``RoadNetwork`` (arc length ``s`` in metres from
the track's start, speed ``v`` in m/s) with the Intelligent Driver Model (``IDM``
parameters per kind) behind its leader, every ``DT`` seconds; all decisions of a step
use the snapshot of the state at its start. Pose tracks are in the town frame (metres,
radians).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation.actors import Actor
from flowslam.simulation.meshes import ActorShape
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.traffic_scripted import EgoGroup
from flowslam.simulation.traffic_spec import DT

IDM = {
    # a (m/s^2), b (m/s^2), headway T (s), minimum gap s0 (m)
    "vehicle": (1.5, 2.0, 1.2, 2.5),
    "walker": (1.0, 1.5, 0.6, 0.6),
    "crosser": (1.0, 1.5, 0.6, 0.6),
}


class Agent:
    """One simulated actor while the simulation runs (``idx``: its row in the records)."""

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


def prepare_speed_caps(tracks) -> None:
    """Per track with a speed cap: the lowest cap of the next ~6 m at every vertex
    (``cap_ahead``) and the lowest of its first ~10 m (``cap_entry``)."""
    for tr in tracks:
        if tr.speed_cap is not None:
            cap = tr.speed_cap
            n = 12  # ~6 m ahead
            padded = np.concatenate([cap, np.full(n, cap[-1])])
            tr.cap_ahead = [float(v) for v in np.lib.stride_tricks.sliding_window_view(padded, n + 1).min(axis=1)]
            tr.cap_entry = float(cap[:20].min())


def run_steps(net, agents: list[Agent], group: EgoGroup, times: np.ndarray, rng: np.random.Generator,
              despawn_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate ``agents`` over ``times``; returns, per agent and step, the track id (-1 when
    not alive), the arc position on it (m) and whether it is alive (each (A, S))."""
    tracks = net.tracks
    trees = {}

    def tree_of(k):
        if k not in trees:
            trees[k] = cKDTree(tracks[k].line.points)
        return trees[k]

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
            _advance(a, tracks, rng, t + DT)
            if a.track == a.grant:
                a.entered = True
            if a.kind == "vehicle" and a.alive and not a.plan:
                # dead end: leave the scene once out of the ego's sight
                end_pos = tracks[a.track].line.points[-1]
                if tracks[a.track].line.length - a.s < a.L and group.distance(end_pos, i) > despawn_distance:
                    a.alive = False
    return rec_track, rec_s, alive


# ------------------------------------------------------------------ per-step helpers
def _extend_plan(a: Agent, tracks, rng) -> None:
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


def _leader(a: Agent, k: int, on_track, tracks, busy) -> tuple[float, float]:
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


def _desired_speed(a: Agent, tracks) -> float:
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


def _idm(a: Agent, gap: float, v_lead: float, v_des: float) -> float:
    acc_max, b, T, s0 = a.params
    v = a.v_snap
    free = acc_max * (1.0 - (v / v_des) ** 4)
    if gap == math.inf:
        return max(free, -9.0)
    gap = max(gap, 0.01)
    s_star = s0 + max(0.0, v * T + v * (v - v_lead) / (2 * math.sqrt(acc_max * b)))
    return min(max(free - acc_max * (s_star / gap) ** 2, -9.0), acc_max)


def _advance(a: Agent, tracks, rng, t_next: float) -> None:
    """Carry ``a`` over track ends: around a sidewalk loop, to the other side of a crosswalk
    (then wait), onto the next planned track, or stop at the end of a dead end."""
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
def agents_to_actors(agents, rec_track, rec_s, alive, times, tracks) -> list[Actor]:
    """Pose tracks of the agents that were ever alive (``id`` still -1), held at their first
    and last alive pose outside their alive span."""
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
        out.append(Actor(-1, a.kind, a.shape, PoseTrack(times, xs, ys, np.unwrap(hs)), al.copy()))
    return out
