"""The cube index (``CubeIndex``, and ``ScanSurface``'s searches through it) answers what
SciPy's KD-tree answers: the same neighbours and distances, on a real KITTI scan and on
constructed cases (a point at exactly the radius, queries far outside, duplicate points,
points the index declines). Metres, the scan's sensor frame."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flowslam.datasets import open_dataset
from flowslam.sceneflow.refinement.clusters import ScanSurface, plane_normals
from flowslam.sceneflow.refinement.compiled_neighbourhoods import CubeIndex


@pytest.fixture(scope="module")
def kitti_scan(kitti_extract):
    """Scan 6 of the KITTI extract within 85 m (horizontally), as the objects stage indexes it."""
    return ScanSurface(open_dataset(kitti_extract)[6].points, 85.0)


def _queries(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Queries near the surface and off it: scan points moved by up to ~0.6 m."""
    rng = np.random.default_rng(seed)
    return points[rng.integers(0, len(points), n)] + rng.normal(0.0, 0.2, (n, 3))


@pytest.mark.parametrize(("edge", "k", "radius"), [(0.3, 1, 0.3), (0.3, 20, 1.0), (0.3, 1, 0.25), (1.0, 5, 0.3)])
def test_cube_index_equals_the_kd_tree_on_a_real_scan(kitti_scan, edge, k, radius):
    points = kitti_scan.points
    index = CubeIndex.build(points, edge)
    tree = cKDTree(points)
    x = _queries(points, 4000, seed=int(100 * radius) + k)
    dist, nb = index.query(x, k, radius)
    expected_dist, expected_nb = tree.query(x, k=k, distance_upper_bound=radius)
    np.testing.assert_array_equal(dist, np.reshape(expected_dist, dist.shape))
    np.testing.assert_array_equal(nb, np.reshape(expected_nb, nb.shape))
    # queries with neighbours, and queries with fewer than k within the radius
    assert np.isfinite(dist[:, 0]).mean() > 0.3 and not np.isfinite(dist[:, -1]).all()


def test_cube_index_radius_is_strict_and_far_queries_find_nothing():
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    index = CubeIndex.build(points, 0.3)
    x = np.array([[0.3, 0.0, 0.0],  # exactly the radius from point 0: not within (SciPy's rule)
                  [0.7, 0.0, 0.0],  # 0.3 from point 1 too
                  [0.71, 0.0, 0.0],  # 0.29 from point 1
                  [-40.0, 0.0, 0.0], [0.0, 1e6, 0.0],  # far outside the points' cubes
                  [np.nan, 0.0, 0.0]])  # not finite: nothing
    dist, nb = index.query(x, 1, 0.3)
    expected_dist, expected_nb = cKDTree(points).query(x[:5], distance_upper_bound=0.3)
    np.testing.assert_array_equal(dist[:5, 0], expected_dist)
    np.testing.assert_array_equal(nb[:5, 0], expected_nb)
    assert list(nb[:, 0]) == [3, 3, 1, 3, 3, 3]
    assert dist[5, 0] == np.inf


def test_cube_index_equal_distances_come_lowest_index_first():
    points = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    dist, nb = CubeIndex.build(points, 0.3).query(np.array([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]]), 4, 0.6)
    assert list(nb[0]) == [4, 0, 1, 2]  # 0, then four at 0.5: the lower indices first
    assert list(nb[1]) == [1, 3, 4, 5]  # two at 0, one at 0.5; none more within 0.6 (index N)
    np.testing.assert_array_equal(dist[1], [0.0, 0.0, 0.5, np.inf])


def test_index_declines_what_its_keys_cannot_count_and_the_surface_asks_the_tree():
    points = np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0], [0.2, 0.0, 0.0]])  # 3.3 M cubes of 0.3 m on x
    assert CubeIndex.build(points, 0.3) is None
    assert CubeIndex.build(np.array([[0.0, 0.0, np.inf]]), 0.3) is None
    scan = ScanSurface(points)
    dist, nb = scan.nearest(np.array([[0.05, 0.0, 0.0], [1e6 + 0.2, 0.0, 0.0], [50.0, 0.0, 0.0]]), 0.3)
    assert list(nb) == [0, 1, 3] and dist[2] == np.inf


def test_scan_surface_nearest_and_normals_equal_the_kd_tree_paths(kitti_scan):
    points = kitti_scan.points
    tree = cKDTree(points, leafsize=16, balanced_tree=False, compact_nodes=False)
    x = _queries(points, 5000, seed=7)
    for expected, got in zip(tree.query(x, distance_upper_bound=0.3), kitti_scan.nearest(x, 0.3)):
        np.testing.assert_array_equal(got, expected)
    idx = np.random.default_rng(8).integers(0, len(points), 3000)
    np.testing.assert_array_equal(kitti_scan.normals(idx, 1.0), plane_normals(tree, points, idx, 1.0))


def test_a_nearest_only_surface_shares_the_index_and_answers_the_same(kitti_scan):
    light = kitti_scan.nearest_only()
    assert light.points is kitti_scan.points and light._cube_index() is kitti_scan._cube_index()
    x = _queries(kitti_scan.points, 3000, seed=9)
    for expected, got in zip(kitti_scan.nearest(x, 0.2), light.nearest(x, 0.2)):
        np.testing.assert_array_equal(got, expected)


def test_cube_index_refuses_a_radius_that_is_not_positive():
    index = CubeIndex.build(np.zeros((3, 3)), 0.3)
    for radius in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError):
            index.query(np.zeros((1, 3)), 1, radius)


def test_within_any_asks_the_tree_where_the_cube_search_declines():
    from flowslam.sceneflow.refinement.compiled_neighbourhoods import near_any_points, within_any

    points = np.array([[0.0, 0.0, 0.0], [2e6, 0.0, 0.0], [0.5, 0.0, 0.0]])
    x = np.array([[0.2, 0.0, 0.0], [2e6 + 0.3, 0.0, 0.0], [-1e6, 0.0, 0.0], [0.75, 0.0, 0.0]])  # 3e6 m wide
    assert near_any_points(points, x, 0.25) is None  # too many cubes of 0.25 m for the packed keys
    expected = np.isfinite(cKDTree(points).query(x, distance_upper_bound=0.25)[0])
    np.testing.assert_array_equal(within_any(x, points, 0.25), expected)
    np.testing.assert_array_equal(expected, [True, False, False, False])
