"""Actors: plausible speeds per kind, never overlapping each other or the ego (checked
independently of the simulator's own collision check), crossing pedestrians; the
collision check itself removes overlapping actors."""

from __future__ import annotations

import numpy as np
import pytest


def _quad(x, y, yaw, length, width):
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    return np.stack([x + c * loc[:, 0] - s * loc[:, 1], y + s * loc[:, 0] + c * loc[:, 1]], 1)


def _overlap(P, Q) -> bool:
    for poly in (P, Q):
        for k in range(4):
            e = poly[(k + 1) % 4] - poly[k]
            n = np.array([-e[1], e[0]])
            a, b = P @ n, Q @ n
            if a.max() < b.min() or b.max() < a.min():
                return False
    return True


@pytest.fixture(scope="module")
def rush(tmp_path_factory):
    from flowslam.simulation import simulate
    from flowslam.simulation.scene_io import load_actors

    out = tmp_path_factory.mktemp("rush") / "seq"
    manifest = simulate(out, preset="rush-hour", frames=40, seed=3, sensor="vlp16", columns=90, workers=1)
    return load_actors(out / "sequences/00/actors.npz"), manifest


def test_speeds_per_kind(rush):
    rec, _ = rush
    limits = {"car": 15.0, "truck": 12.0, "cyclist": 7.0, "pedestrian": 2.0}
    seen = set()
    for k, track in enumerate(rec.actor_tracks):
        shape = rec.shapes[rec.actor_shape[k]]
        v = track.speed()[rec.alive[k][1:]]
        if rec.actor_kinds[k] in ("convoy", "oncoming"):
            assert v.max() <= 12.0  # they drive like the ego (cruise 10 m/s)
            continue
        seen.add(shape.kind)
        assert v.max() <= limits[shape.kind] + 0.05, (shape.kind, v.max())
    assert seen == {"car", "truck", "cyclist", "pedestrian"}
    walkers = [k for k in range(len(rec.actor_kinds)) if rec.actor_kinds[k] == "walker"]
    mean_speed = np.array([rec.actor_tracks[k].speed().mean() for k in walkers])
    assert np.median(mean_speed) > 0.5
    assert "crosser" in set(rec.actor_kinds)


def test_no_actor_overlaps_another_or_the_ego(rush):
    rec, manifest = rush
    ego_len, ego_wid = manifest["sensor"]["vehicle_size"]
    cx = manifest["sensor"]["vehicle_center_x"]
    dims = [rec.shapes[s] for s in rec.actor_shape]
    for i in range(0, len(rec.times), 2):
        t = rec.times[i]
        ex, ey, eyaw = (float(v) for v in rec.ego.at(t))
        quads = [_quad(ex + cx * np.cos(eyaw), ey + cx * np.sin(eyaw), eyaw, ego_len, ego_wid)]
        for k, track in enumerate(rec.actor_tracks):
            if rec.alive[k, i]:
                quads.append(_quad(track.x[i], track.y[i], track.yaw[i], dims[k].length, dims[k].width))
        centers = np.array([q.mean(0) for q in quads])
        radius = np.array([np.linalg.norm(q[0] - q[2]) / 2 for q in quads])
        dist = np.linalg.norm(centers[:, None] - centers[None], axis=2)
        close = np.argwhere(np.triu(dist < radius[:, None] + radius[None], 1))
        for a, b in close:
            assert not _overlap(quads[a], quads[b]), (t, a, b)


def test_collision_check_removes_overlapping_actors():
    from flowslam.simulation.actors import Actor
    from flowslam.simulation.meshes import shape_library
    from flowslam.simulation.paths import PoseTrack
    from flowslam.simulation.traffic_validation import validate

    times = np.arange(0, 1.01, 0.1)
    shapes = shape_library()

    def actor(kind, x):
        return Actor(-1, kind, 0, PoseTrack(times, np.full(len(times), x), np.zeros(len(times)),
                                             np.zeros(len(times))), np.ones(len(times), dtype=bool))

    class Group:
        pass

    group = Group()
    group.times = times
    group.centers = np.full((len(times), 1, 2), 500.0)
    group.ego_yaw = np.zeros(len(times))
    actors = [actor("vehicle", 0.0), actor("vehicle", 3.0), actor("vehicle", 10.0), actor("convoy", 12.0)]
    removed = validate(actors, shapes, group, None)
    # 0 and 3 overlap (the later one goes); 10 overlaps the convoy car at 12 (never removed)
    assert removed == 2
    assert [a.track.x[0] for a in actors] == [0.0, 12.0]
