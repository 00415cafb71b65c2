"""Saving the simulated scene next to the frames (``actors.npz``, ``town.npz``) and loading
``actors.npz`` back (``load_actors``; ``town.npz`` is a plain ``np.load``).

``actors.npz`` (town frame, metres, radians, seconds on the frames' time axis):

- ``ego``: (S_e, 4) ``t, x, y, yaw`` samples of the *sensor frame's* planar pose
  (``T_world_sensor`` at height ``ground_height``); linear interpolation between samples
  is the exact motion used for every ray and every flow vector;
- ``times``: (S,) simulation steps of the actors; ``x, y, yaw``: (A, S) actor poses
  (footprint centre on the ground, heading of the local x axis), interpolated linearly
  in the same way; ``alive``: (A, S);
- ``ids`` (instance ids), ``kinds`` (vehicle / walker / crosser / convoy), ``shape``;
- the shape library: ``shape_names``, ``shape_classes``, ``shape_dims`` (length,
  width, height), ``shape_vertices``/``shape_triangles`` concatenated with
  ``shape_vertex_offsets``/``shape_triangle_offsets`` (local frame: x forward, z up,
  origin on the ground at the footprint centre);
- ``T_town_first``: the first frame's sensor pose in the town frame (``poses/00.txt`` is
  relative to it).

``town.npz``: ``vertices``, ``triangles``, ``labels`` (instance id per triangle, -1 =
ground plane), ``instance_class``, ``instance_kind``, ``class_raster`` (uint8 ground
class, cell (r, c) at ``origin + (c, r) * resolution``), ``origin``, ``resolution``,
``footprints``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowslam.simulation.meshes import ActorShape, Mesh
from flowslam.simulation.paths import PoseTrack, planar_T


def save_actors(path: Path, ego: PoseTrack, actors, T_town_first: np.ndarray, ground_height: float) -> None:
    from flowslam.simulation.writer import save_npz

    A = len(actors.actors)
    S = len(actors.times)
    shapes = actors.shapes
    verts = [s.mesh.vertices for s in shapes]
    tris = [s.mesh.triangles for s in shapes]
    save_npz(Path(path), {
        "ego": ego.as_array(),
        "ground_height": np.array(ground_height),
        "times": actors.times,
        "x": np.array([a.track.x for a in actors.actors]).reshape(A, S),
        "y": np.array([a.track.y for a in actors.actors]).reshape(A, S),
        "yaw": np.array([a.track.yaw for a in actors.actors]).reshape(A, S),
        "alive": np.array([a.alive for a in actors.actors], dtype=bool).reshape(A, S),
        "ids": np.array([a.id for a in actors.actors], dtype=np.int64),
        "kinds": np.array([a.kind for a in actors.actors], dtype="U16"),
        "shape": np.array([a.shape for a in actors.actors], dtype=np.int64),
        "shape_names": np.array([s.name for s in shapes], dtype="U32"),
        "shape_kinds": np.array([s.kind for s in shapes], dtype="U16"),
        "shape_classes": np.array([s.class_id for s in shapes], dtype=np.int64),
        "shape_dims": np.array([[s.length, s.width, s.height] for s in shapes]),
        "shape_vertices": np.concatenate(verts),
        "shape_triangles": np.concatenate(tris).astype(np.int32),
        "shape_vertex_offsets": np.cumsum([0] + [len(v) for v in verts]),
        "shape_triangle_offsets": np.cumsum([0] + [len(t) for t in tris]),
        "T_town_first": T_town_first,
    })


def save_town(path: Path, world) -> None:
    from flowslam.simulation.writer import save_npz

    save_npz(Path(path), {
        "vertices": world.mesh.vertices.astype(np.float32),
        "triangles": world.mesh.triangles.astype(np.int32),
        "labels": world.mesh.labels.astype(np.int32),
        "instance_class": world.instance_class.astype(np.int32),
        "instance_kind": np.array(world.instance_kind, dtype="U16"),
        "class_raster": world.class_raster,
        "origin": world.origin,
        "resolution": np.array(world.resolution),
        "footprints": world.footprints,
    })


@dataclass
class SceneRecord:
    """The content of ``actors.npz`` with interpolating pose tracks (see module doc)."""

    ego: PoseTrack
    ground_height: float
    actor_ids: np.ndarray
    actor_kinds: np.ndarray
    actor_shape: np.ndarray
    actor_tracks: list[PoseTrack]
    alive: np.ndarray
    times: np.ndarray
    shapes: list[ActorShape]
    T_town_first: np.ndarray

    def actor_index(self, instance_id: int) -> int:
        return int(np.flatnonzero(self.actor_ids == instance_id)[0])

    def T_town_sensor(self, t) -> np.ndarray:
        x, y, yaw = self.ego.at(t)
        return planar_T(x, y, yaw, self.ground_height)

    def T_town_actor(self, instance_id: int, t) -> np.ndarray:
        x, y, yaw = self.actor_tracks[self.actor_index(instance_id)].at(t)
        return planar_T(x, y, yaw, 0.0)


def load_actors(path: str | Path) -> SceneRecord:
    z = np.load(Path(path))
    e = z["ego"]
    times = z["times"]
    tracks = [PoseTrack(times, z["x"][k], z["y"][k], z["yaw"][k]) for k in range(len(z["ids"]))]
    vo, to = z["shape_vertex_offsets"], z["shape_triangle_offsets"]
    shapes = []
    for k in range(len(z["shape_names"])):
        v = z["shape_vertices"][vo[k]:vo[k + 1]]
        t = z["shape_triangles"][to[k]:to[k + 1]]
        length, width, height = z["shape_dims"][k]
        shapes.append(ActorShape(str(z["shape_names"][k]), str(z["shape_kinds"][k]), int(z["shape_classes"][k]),
                                 float(length), float(width), float(height),
                                 Mesh(v, t, np.zeros(len(t), dtype=np.int64))))
    return SceneRecord(
        ego=PoseTrack(e[:, 0], e[:, 1], e[:, 2], e[:, 3]), ground_height=float(z["ground_height"]),
        actor_ids=z["ids"], actor_kinds=z["kinds"], actor_shape=z["shape"], actor_tracks=tracks,
        alive=z["alive"], times=times, shapes=shapes, T_town_first=z["T_town_first"],
    )
