"""Static map: a static scene from two poses coincides, dynamic points are absent,
PLY round trip through Open3D, the run_pipeline adapter, the memory bound."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flowslam import geometry
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput
from flowslam.mapping import (
    MapCloud,
    StaticMapBuilder,
    group_keys,
    poses_by_index,
    voxel_downsample,
    voxel_ids,
    voxel_means,
    write_point_cloud,
)

from test_flow_odometry import street_scene
from test_ground_truth_frontends import synthetic_sequence


def test_voxel_downsample_centroids():
    pts = np.array([[0.01, 0.01, 0.01], [0.09, 0.09, 0.09], [0.51, 0.0, 0.0], [-0.01, 0.0, 0.0]])
    out = voxel_downsample(pts, 0.2)
    assert len(out) == 3
    assert any(np.allclose(o, [0.05, 0.05, 0.05]) for o in out)
    assert voxel_downsample(np.zeros((0, 3)), 0.2).shape == (0, 3)


def test_group_keys_numbers_groups_in_key_order_like_np_unique():
    inverse, counts = group_keys(np.array([7, -2, 7, 3, -2, 7], dtype=np.int64))
    assert inverse.tolist() == [2, 0, 2, 1, 0, 2] and counts.tolist() == [2, 1, 3]
    rng = np.random.default_rng(3)
    runs = np.repeat(rng.integers(-50, 50, 400), rng.integers(1, 6, 400))  # scans leave runs of equal keys
    for keys in (runs, rng.integers(0, 1 << 40, 5000), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)):
        _, inv, cnt = np.unique(keys.astype(np.int64), return_inverse=True, return_counts=True)
        got_inv, got_cnt = group_keys(keys.astype(np.int64))
        assert np.array_equal(got_inv, inv.reshape(-1)) and np.array_equal(got_cnt, cnt)


@pytest.mark.parametrize("voxel_size", [0.05, 0.2, 0.75, 3.0])
def test_voxel_means_equal_the_numpy_grouping(voxel_size):
    """``voxel_ids`` / ``voxel_means`` (compiled) give what ``np.unique`` over the integer
    voxel coordinates and ``np.bincount`` sums give, to the bit: voxels in key order,
    points summed in their order; also on a span too wide to pack (the fallback)."""
    rng = np.random.default_rng(4)
    points = np.vstack([street_scene(rng, 20000), rng.uniform(-80, 80, (300, 3))])
    values = rng.random(len(points))
    ijk = np.floor(points / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    expected = np.stack([np.bincount(inverse, points[:, i]) / counts for i in range(3)], axis=1)
    got_inverse, got_counts = voxel_ids(points, voxel_size)
    assert np.array_equal(got_inverse, inverse) and np.array_equal(got_counts, counts)
    centroids, means = voxel_means(points, voxel_size, values)
    assert np.array_equal(centroids, expected) and np.array_equal(means, np.bincount(inverse, values) / counts)
    wide = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0], [0.01, 0.0, 0.0]])  # 1e7 voxels of 0.1 m: the fallback
    assert voxel_ids(wide, 0.1)[0].tolist() == [0, 1, 0]


def test_static_scene_from_two_poses_coincides_and_dynamic_points_are_absent():
    rng = np.random.default_rng(0)
    world = street_scene(rng, 60000)
    lo, hi = np.array([-0.5, 2.5, -1.6]), np.array([1.0, 4.0, 0.6])  # free space for the pedestrian
    world = world[~np.all((world > lo) & (world < hi), axis=1)]
    T_a = np.eye(4)
    T_b = geometry.from_euler("zyx", [7.0, 0.5, -0.3], t=[3.3, 0.7, 0.05], degrees=True)
    # a pedestrian in free space, seen (moving) in scan b only
    person = rng.uniform([0, 3, -1.5], [0.5, 3.5, 0.1], size=(300, 3))
    pts_a = geometry.transform_points(geometry.inv(T_a), world)
    pts_b = np.vstack([geometry.transform_points(geometry.inv(T_b), world),
                       geometry.transform_points(geometry.inv(T_b), person)])
    static_b = np.r_[np.ones(len(world), bool), np.zeros(len(person), bool)]

    builder = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6)
    builder.add(0, pts_a, None)
    builder.add(1, pts_b, static_b)
    one = builder.build({0: T_a})
    both = builder.build({0: T_a, 1: T_b})
    # the two views of the same static scene fall onto the same voxels (grid offsets
    # between the per-scan and the world grid add a fringe, no second copy)
    assert len(one) <= len(both) < 1.6 * len(one)
    d_true, _ = cKDTree(world).query(both)
    assert np.percentile(d_true, 99) < 0.2  # every map point lies on the scene
    # no map point near the pedestrian, which only the dynamic points saw
    d_person, _ = cKDTree(person).query(both)
    assert d_person.min() > 0.15  # (the ground is 0.2 m below)

    wrong = builder.build({0: T_a, 1: np.eye(4)})  # the wrong pose doubles the scene
    assert len(wrong) > 1.8 * len(one)


def test_poses_array_with_indices_and_missing_poses():
    builder = StaticMapBuilder(voxel_size=0.5)
    pts = np.random.default_rng(1).uniform(-5, 5, (500, 3))
    builder.add(10, pts)
    builder.add(11, pts)
    poses = np.stack([np.eye(4), geometry.make_T(t=[100.0, 0, 0])])
    m = builder.build(poses, indices=[10, 11])
    assert m[:, 0].max() > 90 and m[:, 0].min() < -4
    assert len(builder.build(poses[:1], indices=[10])) < len(m)  # scan 11 has no pose: left out
    assert set(poses_by_index(poses, [10, 11])) == {10, 11}
    with pytest.raises(ValueError, match="indices"):
        poses_by_index(poses, [1])


def test_memory_bound_and_storage_precision():
    builder = StaticMapBuilder(voxel_size=0.1, max_points_per_frame=1000)
    pts = np.random.default_rng(2).uniform(-50, 50, (20000, 3))
    pts[0] = [400.0, 0.0, 0.0]  # beyond the int16-centimetre range
    assert builder.add(0, pts) <= 1000
    assert builder.frames[0].dtype == np.int16 and len(builder.frames[0]) <= 1000
    near = np.random.default_rng(3).uniform(-5, 5, (50, 3))
    builder2 = StaticMapBuilder(voxel_size=1e-4)
    builder2.add(0, near)
    np.testing.assert_allclose(np.sort(builder2.points_of(0), axis=0), np.sort(near, axis=0), atol=0.005 + 1e-9)
    b3 = StaticMapBuilder(voxel_size=0.1)
    b3.add(0, np.array([[400.0, 0, 0], [1.0, 2.0, 3.0]]))
    assert b3.dropped_out_of_range == 1 and len(b3.frames[0]) == 1


def test_ply_round_trip_with_open3d(tmp_path: Path):
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(4).uniform(-100, 100, (1234, 3))
    cloud = MapCloud(pts, np.linspace(0.0, 1.0, len(pts), dtype=np.float32))
    path = write_point_cloud(tmp_path / "static_map.ply", cloud)
    legacy = o3d.io.read_point_cloud(str(path))  # the legacy reader takes it too (x y z)
    np.testing.assert_allclose(np.asarray(legacy.points), pts.astype(np.float32), rtol=0, atol=0)
    with pytest.raises(ValueError, match="no points"):
        write_point_cloud(tmp_path / "empty.ply", MapCloud(np.zeros((0, 3)), np.zeros(0, np.float32)))
    with pytest.raises(ValueError, match=".ply or .pcd"):
        write_point_cloud(tmp_path / "map.xyz", cloud)


def test_on_output_adapter_per_point_frontend(tmp_path: Path):
    from flowslam.frontends.ground_truth import GroundTruthFlowFrontend

    frames, poses = synthetic_sequence(n_frames=4)
    frontend = GroundTruthFlowFrontend(use_labels=True)
    builder = StaticMapBuilder(voxel_size=0.2)
    for f in frames:
        builder.on_output(f, frontend.process(f))
    # scans 0..2 via the previous-scan outputs (scan 0's whole-scan entry replaced); the
    # last scan never gets its flow
    assert sorted(builder.frames) == [0, 1, 2]
    world = builder.build(poses, indices=range(4))
    car_world = [geometry.transform_points(poses[k], frames[k].points[frames[k].gt_dynamic]) for k in range(3)]
    d, _ = cKDTree(np.vstack(car_world)).query(world)
    assert d.min() > 0.15  # the moving car is not in the map (the ground is 0.2 m below it)
    assert builder.write(tmp_path / "map.ply", poses) == len(world)


def test_on_output_adapter_without_per_point_outputs():
    """kiss-icp style: no points in the outputs -> each scan's own points, all of them."""
    frames, _ = synthetic_sequence(n_frames=3)
    builder = StaticMapBuilder(voxel_size=0.2)
    for f in frames:
        builder.on_output(f, FrontendOutput(index=f.index, T_prev_curr=None if f.index == 0 else np.eye(4)))
    assert sorted(builder.frames) == [0, 1, 2]
    car = frames[1].points[frames[1].gt_dynamic]
    d, _ = cKDTree(builder.points_of(1)).query(car)
    assert np.median(d) < 0.2  # no dynamic removal: the car is in


@pytest.mark.parametrize("frontend", ["gt", "gt-flow"])
def test_run_pipeline_on_av2_writes_a_static_map(av2_log: Path, tmp_path: Path, frontend: str):
    """End to end: frontend -> odometry backend, the map via on_output, the final poses.
    ``gt`` removes the 2037 moving points; ``gt-flow`` (no segmentation) keeps them."""
    o3d = pytest.importorskip("open3d")
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend

    config = load_config()
    ds = open_dataset(av2_log)
    builder = StaticMapBuilder(voxel_size=0.2)
    result = run_pipeline(ds, make_frontend(frontend, config), make_backend("odometry", config),
                          on_output=builder.on_output)
    assert result.error is None and result.indices == [0, 1]
    assert sorted(builder.frames) == [0]  # scan 1 (the last) has no flow
    n = builder.write(tmp_path / "static_map.ply", result.poses, result.indices)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "static_map.ply"))
    assert len(cloud.points) == n > 20000
    dyn_world = ds[0].points[ds[0].gt_dynamic]  # scan 0 is the world frame
    d, _ = cKDTree(np.asarray(cloud.points)).query(dyn_world)
    near = float(np.mean(d < 0.1))  # share of moving points with a map point within 10 cm
    if frontend == "gt":
        assert near < 0.02  # gone (a few touch static neighbours)
    else:
        assert near > 0.3


def _drive_through_street(n_scans: int, seed: int = 5):
    """A street 160 m long, scanned every 0.8 m (gentle yaw) by a 30 m sensor: each scan a
    fresh random half of the surface points in range (as beams hit surfaces anew)."""
    rng = np.random.default_rng(seed)
    world = np.vstack([street_scene(rng, 120000) + [80.0 * c, 0.0, 0.0] for c in range(3)])
    poses = [geometry.from_euler("z", 0.3 * np.sin(k / 7.0), t=[-30.0 + 0.8 * k, 0.5 * np.sin(k / 11.0), 0.0],
                                 degrees=True) for k in range(n_scans)]
    frames = []
    for k, T in enumerate(poses):
        near = world[(np.linalg.norm(world[:, :2] - T[:2, 3], axis=1) < 30.0) & (rng.random(len(world)) < 0.5)]
        pts = geometry.transform_points(geometry.inv(T), near) + rng.normal(0.0, 0.01, near.shape)
        frames.append(Frame(index=k, timestamp=0.1 * k, points=pts))
    return world, np.stack(poses), frames


def _feed(builder: StaticMapBuilder, poses: np.ndarray, frames, no_motion_at: int | None = None) -> None:
    for k, f in enumerate(frames):
        T = None if k == 0 or k == no_motion_at else geometry.relative(poses[k - 1], poses[k])
        builder.on_output(f, FrontendOutput(index=f.index, T_prev_curr=T))


def test_voxels_seen_by_recent_scans_are_stored_once_and_the_map_stays_re_expressible():
    """Scans given with a *drifting* odometry (on_output) keep only the voxels no recent scan
    saw (decided in the drifting odometry frame): far fewer points than every scan whole,
    and rebuilt with the true ("loop-corrected") poses the same map as the per-scan store
    gives, on the scene: each voxel moves with the scan that keeps it."""
    world, poses, frames = _drive_through_street(60)
    drift = np.stack([geometry.from_euler("z", 0.02 * k, t=[0.0, 0.0002 * k**2, 0.0], degrees=True) @ T
                      for k, T in enumerate(poses)])  # 1.2 deg and 0.7 m off after 60 scans (~1%)
    dedup = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6)
    whole = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6, dedup_window=0)
    _feed(dedup, drift, frames)
    _feed(whole, drift, frames)
    assert sorted(dedup.frames) == list(range(60)) and dedup.deduplicated > 0
    assert dedup.n_points < 0.15 * whole.n_points  # the street seen again and again is kept once
    a, b = dedup.build(poses), whole.build(poses)
    # fewer map points: the per-scan store also keeps the fringe of centroids that scans
    # sampling a voxel differently put into the neighbouring world voxels
    assert 0.75 * len(b) < len(a) <= len(b)
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    assert np.percentile(d_ab, 99) < 0.15 and np.percentile(d_ba, 95) < 0.15  # the same surfaces
    d_true, _ = cKDTree(world).query(a)
    assert np.percentile(d_true, 99) < 0.15  # on the scene
    seen = world[np.abs(world[:, 0]) < 40.0]  # scene points every scan pass went near
    assert np.mean(cKDTree(a).query(seen)[0] < 0.15) > 0.98  # and covering it (the store: 0.9999)
    # a rigid change of the world frame moves the map rigidly
    C = geometry.from_euler("z", 30.0, t=[5.0, -3.0, 0.2], degrees=True)
    moved, expected = dedup.build(C @ poses), geometry.transform_points(C, a)  # (re-voxelised on the world grid)
    assert np.percentile(cKDTree(expected).query(moved)[0], 99) < 0.15
    assert np.percentile(cKDTree(moved).query(expected)[0], 95) < 0.15


def test_recent_voxels_are_bounded_and_a_restarted_chain_keeps_its_scan_whole():
    _, poses, frames = _drive_through_street(50)
    builder = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6, dedup_window=10)
    _feed(builder, poses, frames, no_motion_at=30)
    recent = builder._recent
    assert np.all(recent.last >= 49 - 2 * 10) and np.all(np.diff(recent.keys) > 0)  # pruned, sorted, unique
    n_voxels = len(voxel_downsample(frames[30].points, 0.2))
    assert len(builder.frames[30]) == n_voxels  # no odometry into scan 30: kept whole
    assert len(builder.frames[31]) < 0.5 * n_voxels  # and the new chain deduplicates again
    # scans added without a pose are kept whole, as before
    plain = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6)
    plain.add(0, frames[0].points)
    plain.add(1, frames[1].points)
    assert len(plain.frames[1]) == len(voxel_downsample(frames[1].points, 0.2))
    with pytest.raises(ValueError, match="dedup_window"):
        StaticMapBuilder(dedup_window=-1)


@pytest.mark.parametrize("voxel", [0.3, 0.75, 1.0])
def test_open3d_voxel_means_give_open3ds_voxels_and_numbers(kitti_extract, voxel):
    """``open3d_voxel_means`` (compiled) gives the centroids (and mean normals) of Open3D's
    ``voxel_down_sample`` bit for bit, only in voxel-key order: the same grid (the kept
    points' minimum minus half a voxel), the same sums in point order."""
    import open3d as o3d

    from flowslam.compiled_voxels import open3d_voxel_means
    from flowslam.datasets import open_dataset

    def rows(a: np.ndarray) -> np.ndarray:
        return a[np.lexsort(a.T[::-1])]

    points = open_dataset(kitti_extract)[5].points.astype(np.float64)
    keep = np.einsum("ij,ij->i", points, points) < 60.0**2
    normals = np.random.default_rng(1).normal(size=points.shape)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
    cloud.normals = o3d.utility.Vector3dVector(normals[keep])
    theirs = cloud.voxel_down_sample(voxel)
    ours, our_normals = open3d_voxel_means(points, voxel, keep, normals)
    assert len(ours) == len(theirs.points) > 1000
    np.testing.assert_array_equal(rows(np.hstack([ours, our_normals])),
                                  rows(np.hstack([np.asarray(theirs.points), np.asarray(theirs.normals)])))
    keys = np.floor((ours - (points[keep].min(axis=0) - voxel / 2)) / voxel)
    assert np.all(np.diff(keys[:, 0]) >= 0)  # key order: x first
    empty, none = open3d_voxel_means(points, voxel, np.zeros(len(points), dtype=bool))
    assert empty.shape == (0, 3) and none is None
