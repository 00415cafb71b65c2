"""The objects stage's compiled ICP (``flowslam.sceneflow.refinement.compiled_icp``) equals
Open3D's point-to-point ``registration_icp`` run stage by stage with the same criteria, and
its search grid finds the same nearest points as SciPy's KD-tree. Metres throughout."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from flowslam import geometry
from flowslam.geometry import transform_points
from flowslam.sceneflow.refinement import compiled_icp
from flowslam.sceneflow.refinement.compiled_icp import IcpTarget, register

REG = o3d.pipelines.registration


def _open3d(p: np.ndarray, box: np.ndarray, T: np.ndarray, stages, iterations: int) -> np.ndarray:
    """Open3D's point-to-point ICP of ``p`` onto ``box`` from ``T``, once per stage."""
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(box))
    criteria = REG.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=iterations)
    for max_dist in stages:
        T = np.asarray(REG.registration_icp(src, tgt, max_dist, T, REG.TransformationEstimationPointToPoint(),
                                            criteria).transformation)
    return T


def _car_scene(seed: int):
    """(car points at k-1, target box at k, true motion): a noisy road, a wall and a
    box-shaped car moved 1.2 m and turned 3 degrees."""
    rng = np.random.default_rng(seed)
    n = 8000
    road = np.column_stack([rng.uniform(-10, 20, n), rng.uniform(-8, 8, n), -1.7 + 0.03 * rng.standard_normal(n)])
    wall = np.column_stack([rng.uniform(-10, 20, n // 4), np.full(n // 4, 8.0) + 0.02 * rng.standard_normal(n // 4),
                            rng.uniform(-1.7, 3.0, n // 4)])
    car = np.column_stack([rng.uniform(4, 8, 600), rng.uniform(-1, 1, 600), rng.uniform(-1.3, -0.2, 600)])
    motion = geometry.from_euler("z", np.radians(3.0), t=[1.2, 0.1, 0.0])
    return car, np.vstack([road, wall, transform_points(motion, car)]), motion


@pytest.mark.parametrize("seed, start_x", [(0, 0.9), (1, 1.1), (2, 0.0), (3, 1.6)])
def test_register_equals_open3d_stage_by_stage(seed, start_x):
    """From 0.1-0.3 m off both find the car's motion; from 1.2 m off (and beyond) both
    slide it somewhere else, the same way."""
    car, box, motion = _car_scene(seed)
    start = geometry.from_euler("z", 0.0, t=[start_x, 0.0, 0.0])
    stages, iterations = [1.0, 0.3, 0.1], 15
    ours = register(car, IcpTarget(box), start, stages, iterations)
    theirs = _open3d(car, box, start, stages, iterations)
    np.testing.assert_allclose(transform_points(ours, car), transform_points(theirs, car), atol=1e-9)
    if abs(start_x - 1.2) <= 0.3:
        assert geometry.translation_norm(ours @ geometry.inv(motion)) < 0.05


def test_register_equals_open3d_on_real_kitti_patches(kitti_extract):
    """Patches of real KITTI scan 1 (the points within 4 m of a few centres) registered onto
    scan 2 from the identity and from 0.5 m off: every landing within 1e-9 m of Open3D's."""
    from flowslam.datasets import open_dataset

    ds = open_dataset(kitti_extract)
    source, target = ds[1].points[:, :3].astype(np.float64), ds[2].points[:, :3].astype(np.float64)
    tree = IcpTarget(target)
    rng = np.random.default_rng(3)
    for centre in source[rng.choice(len(source), 6, replace=False)]:
        patch = source[np.linalg.norm(source - centre, axis=1) < 4.0]
        patch = patch[rng.permutation(len(patch))[:400]]
        for offset in (0.0, 0.5):
            start = geometry.from_euler("z", 0.0, t=[offset, 0.0, 0.0])
            ours = register(patch, tree, start, [1.0, 0.3, 0.1], 15)
            theirs = _open3d(patch, target, start, [1.0, 0.3, 0.1], 15)
            np.testing.assert_allclose(transform_points(ours, patch), transform_points(theirs, patch), atol=1e-9)


@pytest.mark.parametrize("n", [0, 1, 5, 33, 5000])
def test_nearest_within_reach_equals_scipy(n):
    """Nearest target point within 0.3 m, or none, as ``cKDTree.query(distance_upper_bound)``,
    also with duplicated target points (any one of equal nearest points is right)."""
    rng = np.random.default_rng(n)
    points = rng.uniform(-2, 2, (n, 3))
    if n > 1:
        points[n // 2:] = points[: n - n // 2]  # every point twice
        points[: n // 4, 2] = 0.0  # a flat patch
    target = IcpTarget(points)
    ordered, order = target._grid[0], target._grid[1]
    queries = rng.uniform(-2.5, 2.5, (2000, 3))
    src, dst = np.empty(len(queries), np.int64), np.empty(len(queries), np.int64)
    hints = np.full(len(queries), -1, np.int64)
    m, fitness, rmse = compiled_icp._match(queries, 0.3, ordered, *target._grid[2:], src, dst, hints)
    expected, _ = cKDTree(points).query(queries, distance_upper_bound=0.3) if n else (np.full(2000, np.inf), None)
    found = np.isfinite(expected)
    assert m == found.sum() and np.array_equal(src[:m], np.flatnonzero(found))
    got = np.linalg.norm(ordered[dst[:m]] - queries[src[:m]], axis=1)
    np.testing.assert_allclose(got, expected[found], atol=1e-12)
    assert np.array_equal(ordered, points[order])
    if m:
        assert fitness == pytest.approx(m / len(queries)) and rmse == pytest.approx(np.sqrt(np.mean(got ** 2)))


def test_register_without_correspondences_keeps_the_start():
    """Nothing within reach (or an empty target): the start comes back, as from Open3D."""
    car, box, _ = _car_scene(0)
    start = geometry.from_euler("z", 0.2, t=[50.0, 0.0, 0.0])
    np.testing.assert_array_equal(register(car, IcpTarget(box), start, [1.0, 0.3], 15), start)
    np.testing.assert_array_equal(register(car, IcpTarget(np.empty((0, 3))), start, [1.0], 15), start)
    np.testing.assert_allclose(_open3d(car, box, start, [1.0, 0.3], 15), start, atol=0)


def _turn_deg(T: np.ndarray, start: np.ndarray) -> float:
    """Angle (deg) of the rotation from ``start``'s to ``T``'s."""
    R = T[:3, :3] @ start[:3, :3].T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def test_register_gives_up_when_an_iteration_turns_beyond_the_limit():
    """A sparse L-shaped object whose only target is itself turned 25 deg about its corner:
    the free ICP turns it that far; with a 10 deg limit the registration is given up
    (None); with a 60 deg limit, which it never reaches, the result is the free one bit for
    bit; the car scene's 3 deg motion passes a 10 deg limit unchanged."""
    rng = np.random.default_rng(7)
    arm = rng.uniform(0.0, 1.5, 40)
    obj = np.vstack([np.column_stack([arm, np.zeros(40), rng.uniform(0, 0.3, 40)]),
                     np.column_stack([np.zeros(40), arm, rng.uniform(0, 0.3, 40)])])
    turned = transform_points(geometry.from_euler("z", np.radians(25.0)), obj)
    start = np.eye(4)
    free = register(obj, IcpTarget(turned), start, [1.0, 0.3], 15)
    assert abs(_turn_deg(free, start) - 25.0) < 0.5
    assert register(obj, IcpTarget(turned), start, [1.0, 0.3], 15, max_turn_rad=np.radians(10.0)) is None
    limited = register(obj, IcpTarget(turned), start, [1.0, 0.3], 15, max_turn_rad=np.radians(60.0))
    np.testing.assert_array_equal(limited, free)
    car, box, _ = _car_scene(0)
    car_start = geometry.from_euler("z", 0.0, t=[1.0, 0.0, 0.0])
    np.testing.assert_array_equal(register(car, IcpTarget(box), car_start, [1.0, 0.3, 0.1], 15,
                                           max_turn_rad=np.radians(10.0)),
                                  register(car, IcpTarget(box), car_start, [1.0, 0.3, 0.1], 15))


def _open3d_point_to_plane(p, target, normals, T, stages, iterations):
    """Open3D's Tukey point-to-plane ICP (kernel = the stage's distance), once per stage."""
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.normals = o3d.utility.Vector3dVector(normals)
    criteria = REG.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=iterations)
    for max_dist in stages:
        T = np.asarray(REG.registration_icp(src, tgt, max_dist, T,
                                            REG.TransformationEstimationPointToPlane(REG.TukeyLoss(k=max_dist)),
                                            criteria).transformation)
    return T


def test_point_to_plane_equals_open3d_on_real_kitti_refinement_inputs(kitti_extract):
    """The static refinement's inputs of real KITTI pairs (voxel centroids of scan k-1, the
    planar points and normals of scan k), from the GT motion and from 0.3 m / 1 degree off:
    every landing within 1e-9 m of Open3D's ``registration_icp``."""
    from scipy.spatial import cKDTree

    from flowslam.config import FlowRefinementConfig
    from flowslam.datasets import open_dataset
    from flowslam.sceneflow.refinement.static import _planar_points, _voxel_centroids

    c = FlowRefinementConfig()
    ds = open_dataset(kitti_extract)
    for k in (3, 9):
        source = _voxel_centroids(ds[k - 1].points, c.voxel_m, c.max_range_m)[::3]
        target = _voxel_centroids(ds[k].points, c.voxel_m, c.max_range_m)
        planar, normals = _planar_points(target, c, cKDTree(target))
        motion = geometry.inv(ds[k].gt_pose) @ ds[k - 1].gt_pose
        for start in (motion, geometry.from_euler("z", np.radians(1.0), t=[0.3, 0.0, 0.0]) @ motion):
            ours = compiled_icp.register_point_to_plane(source, IcpTarget(planar), normals, start,
                                                        c.correspondence_m, c.max_iterations)
            theirs = _open3d_point_to_plane(source, planar, normals, start, c.correspondence_m, c.max_iterations)
            np.testing.assert_allclose(transform_points(ours, source), transform_points(theirs, source), atol=1e-9)


def test_point_to_plane_without_usable_matches_keeps_the_start():
    """No target point within reach, or every residual beyond the Tukey kernel (zero
    weights: the normal equations are all zero, solved as no motion): the start comes
    back, as from Open3D."""
    car, box, _ = _car_scene(1)
    normals = np.tile([0.0, 0.0, 1.0], (len(box), 1))
    far = geometry.from_euler("z", 0.1, t=[60.0, 0.0, 0.0])
    np.testing.assert_array_equal(compiled_icp.register_point_to_plane(car, IcpTarget(box), normals, far, [1.0], 15),
                                  far)
    flat = np.column_stack([np.random.default_rng(0).uniform(-5, 5, (500, 2)), np.zeros(500)])
    above = flat[:50] + [0.0, 0.0, 0.5]  # every residual 0.5 m, beyond a 0.3 m kernel
    got = compiled_icp.register_point_to_plane(above, IcpTarget(flat), np.tile([0.0, 0.0, 1.0], (500, 1)),
                                               np.eye(4), [0.6, 0.3], 10)
    np.testing.assert_allclose(got, _open3d_point_to_plane(above, flat, np.tile([0.0, 0.0, 1.0], (500, 1)),
                                                           np.eye(4), [0.6, 0.3], 10), atol=1e-12)


def test_ldlt_solve_equals_numpy_and_zeroes_null_directions():
    rng = np.random.default_rng(5)
    for _ in range(20):
        J = rng.normal(size=(40, 6)) * rng.uniform(0.01, 10, 6)
        A, b = J.T @ J, rng.normal(size=6)
        np.testing.assert_allclose(compiled_icp._ldlt_solve(A, b), np.linalg.solve(A, b), rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(compiled_icp._ldlt_solve(np.zeros((6, 6)), np.ones(6)), np.zeros(6))
    A = np.diag([4.0, 0.0, 1.0, 2.0, 0.0, 3.0])  # two null directions: their unknowns are 0
    np.testing.assert_allclose(compiled_icp._ldlt_solve(A, np.ones(6)), [0.25, 0, 1, 0.5, 0, 1 / 3], atol=1e-15)


def test_nearest_within_equals_scipy_query():
    rng = np.random.default_rng(7)
    points = rng.uniform(-3, 3, (4000, 3))
    queries = rng.uniform(-3.5, 3.5, (3000, 3))
    dist, idx = cKDTree(points).query(queries, distance_upper_bound=0.2)
    got = compiled_icp.nearest_within(IcpTarget(points), queries, 0.2)
    np.testing.assert_array_equal(got, np.where(np.isfinite(dist), idx, -1))


def test_object_polish_equals_open3d_point_to_plane_on_estimated_normals():
    """The objects stage's point-to-plane polish (Open3D's normals, the compiled ICP without
    a kernel, whose sums do not depend on threads) lands the car where Open3D's
    ``registration_icp`` on the same target points and normals does, from the true motion
    and from 0.2 m / 1 degree off."""
    from flowslam.config.ssf import ObjectRefinementConfig
    from flowslam.sceneflow.refinement.objects import _near_landing, _polish

    c = ObjectRefinementConfig()
    max_dist = c.correspondence_m[-1]
    criteria = REG.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=c.max_iterations)
    for seed in (0, 1, 2):
        car, box, motion = _car_scene(seed)
        for start in (motion, geometry.from_euler("z", np.radians(1.0), t=[0.2, 0.0, 0.0]) @ motion):
            ours = _polish(car, box, start, c)
            tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_near_landing(box, car, start, max_dist)))
            tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=c.plane_stage_radius_m, max_nn=20))
            src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(car))
            theirs = np.asarray(REG.registration_icp(src, tgt, max_dist, start,
                                                     REG.TransformationEstimationPointToPlane(), criteria).transformation)
            np.testing.assert_allclose(transform_points(ours, car), transform_points(theirs, car), atol=1e-6)
            assert geometry.translation_norm(ours @ geometry.inv(motion)) < 0.05


def test_nearest_within_on_a_wide_cloud_with_non_finite_points_equals_scipy():
    """A cloud 400 m wide (its grid gets cubes larger than ``CELL_M``, within the cap),
    with NaN and infinite target points (never matched) and queries: far outside the
    grid, non-finite (none), on a point, and at the reach from one, against SciPy."""
    rng = np.random.default_rng(11)
    points = np.vstack([rng.uniform(-200, 200, (3000, 3)) * [1, 1, 0.02], [[np.nan, 0, 0], [0, np.inf, 0]]])
    target = IcpTarget(points)
    assert target._grid[5] > compiled_icp.CELL_M and len(target._grid[0]) == 3000
    dims = target._grid[4]
    assert dims.prod() <= compiled_icp.MAX_CELLS_PER_POINT * len(points) + 4096
    queries = np.vstack([rng.uniform(-210, 210, (2000, 3)) * [1, 1, 0.05], [[1e4, 0, 0], [np.nan, 0, 0]],
                         points[:1], points[1:2] + [2.5, 0, 0]])
    finite = np.isfinite(queries).all(axis=1)
    dist, idx = cKDTree(points[:3000]).query(queries[finite], distance_upper_bound=2.5)
    got = compiled_icp.nearest_within(target, queries, 2.5)
    np.testing.assert_array_equal(got[finite], np.where(np.isfinite(dist), idx, -1))
    assert got[2000] == -1 and got[2001] == -1 and got[2002] == 0
