"""Footprint overlap checks of the traffic simulation: oriented-rectangle corners, the
separating-axis test, the scripted actors that would clash with the ego or the convoy,
and ``validate``, the final non-overlap check that removes offending actors.

Footprints are oriented rectangles on the ground in the town frame (metres, radians):
centre ``x, y``, heading ``yaw`` of the long (local x) axis, half length ``hl`` along
it and half width ``hw`` across. Checks run at every simulation step (``DT``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from flowslam.simulation.actors import Actor
from flowslam.simulation.ego_path import EgoMotion
from flowslam.simulation.town import StaticWorld
from flowslam.simulation.traffic_scripted import EgoGroup


def footprint_corners(cx, cy, yaw, hl, hw) -> np.ndarray:
    """(K, 4, 2) corners of K oriented rectangles (all arguments (K,))."""
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


def scripted_clashes(scripted: list[Actor], shapes, ego: EgoMotion, times, ego_size) -> np.ndarray:
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
        A = footprint_corners(a.track.x, a.track.y, a.track.yaw, np.full(n, hl), np.full(n, hw))
        for rx, ry, ryaw, rhl, rhw in ref:
            near = np.hypot(a.track.x - rx, a.track.y - ry) < np.hypot(hl, hw) + np.hypot(rhl, rhw)
            if near.any():
                B = footprint_corners(rx[near], ry[near], ryaw[near], np.full(near.sum(), rhl),
                                      np.full(near.sum(), rhw))
                if rectangles_overlap(A[near], B).any():
                    out[j] = True
                    break
    return out


def validate(actors: list[Actor], shapes, group: EgoGroup, world: StaticWorld | None,
             ego_size=(4.6, 1.9), report: list | None = None) -> int:
    """Remove (in place) every non-convoy actor that ever overlaps another actor, the ego
    or a static obstacle; returns how many were removed. ``report`` (if given) gets a
    ``(kind, other kind)`` pair per overlap found."""
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
            hit = rectangles_overlap(footprint_corners(X[p, i], Y[p, i], H[p, i], HL[p], HW[p]),
                                     footprint_corners(X[q, i], Y[q, i], H[q, i], HL[q], HW[q]))
            flag(p[hit], q[hit])
    # actor vs ego, all steps at once
    ec = group.centers[:, 0]
    ehl, ehw = ego_size[0] / 2, ego_size[1] / 2
    d = np.hypot(X - ec[None, :, 0], Y - ec[None, :, 1])
    ka, st = np.nonzero(alive & (d < R[:, None] + np.hypot(ehl, ehw) + 0.1))
    if len(ka):
        n = len(ka)
        ego_c = footprint_corners(ec[st, 0], ec[st, 1], group.ego_yaw[st], np.full(n, ehl), np.full(n, ehw))
        hit = rectangles_overlap(footprint_corners(X[ka, st], Y[ka, st], H[ka, st], HL[ka], HW[ka]), ego_c)
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
                hit = rectangles_overlap(
                    footprint_corners(X[a_k, s_k], Y[a_k, s_k], H[a_k, s_k], HL[a_k], HW[a_k]),
                    footprint_corners(f[j, 0], f[j, 1], f[j, 2], f[j, 3], f[j, 4]))
                flag(np.unique(a_k[hit]), what="static")
                if report is not None:
                    report.extend(("static-kind", world.instance_kind[int(f[jj, 5])]) for jj in np.unique(j[hit]))
    for k in sorted(np.flatnonzero(bad), reverse=True):
        del actors[k]
    return int(bad.sum())
