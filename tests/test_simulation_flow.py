"""Scene-flow ground truth checked geometrically, from the files on disk, without and
with motion distortion:

- static points: ``p + flow`` = the point moved by the relative sensor pose (1e-5 m),
  per point (its own firing time) when the sweep is distorted;
- dynamic points: ``p + flow`` = the surface point carried by its actor's motion (1e-4 m),
  and that point lies on the actor's mesh at both times;
- static points lie on the town mesh or the ground; ``flow_compensated`` is zero for them
  and the object's own motion for dynamic points; ``dynamic`` flags match the motion.
"""

from __future__ import annotations

import numpy as np
import pytest

from flowslam import geometry
from flowslam.simulation.labels import ACTOR_ID_BASE


@pytest.fixture(scope="module", params=[False, True], ids=["instantaneous", "distorted"])
def sim(request, tmp_path_factory):
    from flowslam.datasets import open_dataset
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("flow") / "seq"
    simulate(out, preset="dt", frames=4, seed=11, sensor="vlp16", columns=720, range_noise=0.0, dropout=0.0,
             distortion=request.param, workers=1)
    return open_dataset(out), request.param


def _apply(T, p):
    return np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]


def _apply_inv(T, p):
    return np.einsum("nji,nj->ni", T[:, :3, :3], p - T[:, :3, 3])


def test_static_flow_is_the_relative_pose(sim):
    ds, distortion = sim
    scene = ds.scene
    for i in range(len(ds) - 1):
        f = ds[i]
        t0, t1 = ds.timestamps[i], ds.timestamps[i + 1]
        tau = f.point_times if distortion else np.zeros(len(f.points))
        if distortion:
            assert f.point_times is not None and f.point_times.max() > 0.09
        else:
            assert f.point_times is None
        A, B = scene.T_town_sensor(t0 + tau), scene.T_town_sensor(t1 + tau)
        static = f.gt_instance < ACTOR_ID_BASE
        assert static.sum() > 1000
        expected = _apply_inv(B, _apply(A, f.points))
        err = np.abs(f.points + f.gt_flow - expected)[static].max()
        assert err < 1e-5
        # and it is what the frame-to-frame pose predicts, exactly only without distortion
        T_next_curr = geometry.relative(ds.gt_poses[i + 1], ds.gt_poses[i])
        naive = geometry.transform_points(T_next_curr, f.points) - f.points
        naive_err = np.abs(naive - f.gt_flow)[static].max()
        if distortion:
            assert naive_err > 1e-3  # the sweep is distorted: one pose per frame is not enough
        else:
            assert naive_err < 1e-5
        assert np.abs(f.extras["flow_compensated"][static]).max() == 0.0
        assert not f.gt_dynamic[static].any()


def test_static_points_lie_on_the_world(sim):
    import open3d as o3d

    ds, distortion = sim
    town = np.load(ds.sequence_dir / "town.npz")
    objects = town["labels"] >= 0
    scene_o3d = o3d.t.geometry.RaycastingScene()
    scene_o3d.add_triangles(town["vertices"], town["triangles"][objects].astype(np.uint32))
    f = ds[1]
    tau = f.point_times if distortion else np.zeros(len(f.points))
    world = _apply(ds.scene.T_town_sensor(ds.timestamps[1] + tau), f.points)
    ground = f.gt_instance == -1
    assert ground.any() and np.abs(world[ground, 2]).max() < 1e-4
    things = (f.gt_instance >= 0) & (f.gt_instance < ACTOR_ID_BASE)
    d = scene_o3d.compute_distance(o3d.core.Tensor(world[things].astype(np.float32))).numpy()
    assert d.max() < 2e-3
    # the instance of each point is the instance of the triangle it lies on
    hit = scene_o3d.compute_closest_points(o3d.core.Tensor(world[things].astype(np.float32)))
    tri_label = town["labels"][objects][hit["primitive_ids"].numpy()]
    assert np.mean(tri_label == f.gt_instance[things]) > 0.99


def test_dynamic_flow_is_the_actor_motion(sim):
    import open3d as o3d

    ds, distortion = sim
    scene = ds.scene
    checked = 0
    for i in range(len(ds) - 1):
        f = ds[i]
        t0, t1 = ds.timestamps[i], ds.timestamps[i + 1]
        tau = f.point_times if distortion else np.zeros(len(f.points))
        A, B = scene.T_town_sensor(t0 + tau), scene.T_town_sensor(t1 + tau)
        world = _apply(A, f.points)
        for inst in np.unique(f.gt_instance[f.gt_instance >= ACTOR_ID_BASE]):
            m = f.gt_instance == inst
            Ta, Tb = scene.T_town_actor(inst, t0 + tau[m]), scene.T_town_actor(inst, t1 + tau[m])
            local = _apply_inv(Ta, world[m])
            moved = _apply(Tb, local)
            expected = _apply_inv(B[m], moved)
            assert np.abs(f.points[m] + f.gt_flow[m] - expected).max() < 1e-4
            own = np.einsum("nji,nj->ni", A[m][:, :3, :3], moved - world[m])
            assert np.abs(f.extras["flow_compensated"][m] - own).max() < 1e-4
            speed = np.linalg.norm(moved - world[m], axis=1) / (t1 - t0)
            assert np.array_equal(f.gt_dynamic[m], speed > 0.5)
            # the surface point is on the actor's mesh, at t and (carried) at t+1
            shape = scene.shapes[scene.actor_shape[scene.actor_index(inst)]]
            mesh = o3d.t.geometry.RaycastingScene()
            mesh.add_triangles(shape.mesh.vertices.astype(np.float32), shape.mesh.triangles.astype(np.uint32))
            d = mesh.compute_distance(o3d.core.Tensor(local.astype(np.float32))).numpy()
            assert d.max() < 1e-3
            local_next = _apply_inv(Tb, _apply(B[m], f.points[m] + f.gt_flow[m]))
            assert np.abs(local_next - local).max() < 1e-4
            checked += int(m.sum())
    assert checked > 500  # the dt preset has moving actors in view (at least its lead car)
    assert sum(ds[i].gt_dynamic.sum() for i in range(len(ds))) > 200
