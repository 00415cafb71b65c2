"""Spawning the simulated (non-scripted) actors near the ego route: vehicles and
cyclists on plain lanes, walkers on the sidewalk loops (added to the network as
``walk`` tracks), crossers waiting at crosswalks.

Densities come from ``TrafficSpec`` (per km of usable track within ``spawn_radius`` /
``walker_radius`` metres of the driven part of the ego route, town frame). Desired
speeds (m/s): cars 8-15, trucks 7-12, cyclists 3-7, walkers 0.6-1.8, crossers 1.0-1.8;
each actor starts at 40-100 % of it (crossers start at rest, waiting). Spawn positions on
one track are kept apart (clearance: the vehicle length + 6 m, 1.2 m for a pedestrian).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation.meshes import shapes_of_kind
from flowslam.simulation.traffic_spec import TrafficSpec
from flowslam.simulation.traffic_stepping import Agent


def _near_route(points: np.ndarray, route_tree: cKDTree, radius: float) -> np.ndarray:
    d, _ = route_tree.query(points, distance_upper_bound=radius)
    return np.isfinite(d)


def spawn_agents(net, world, ego, spec: TrafficSpec, shapes, rng) -> list[Agent]:
    """The agents at time 0, ``Agent.idx`` = their position in the returned list."""
    sampled = ego.route.resampled(2.0)
    # only the part of the route that this sequence drives (plus a margin)
    s_lo = ego.s_at(ego.frame_times[0]) - 50.0
    s_hi = ego.s_at(ego.frame_times[-1]) + 150.0
    keep = (sampled.s >= s_lo) & (sampled.s <= s_hi)
    route_tree = cKDTree(sampled.points[keep] if keep.any() else sampled.points)
    agents: list[Agent] = []
    occupied: dict[int, list] = {}

    def place(kind, shape_id, track, s, v0):
        shape = shapes[shape_id]
        lst = occupied.setdefault(track, [])
        clearance = (shape.length + 6.0) if kind == "vehicle" else 1.2
        if any(abs(s - s2) < clearance / 2 + l2 / 2 for s2, l2 in lst):
            return None
        lst.append((s, clearance))
        a = Agent(len(agents), kind, shape, shape_id, v0, track, s, v0 * rng.uniform(0.4, 1.0))
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
