"""The faster computations of the static refinement (``flowslam.sceneflow.refinement.static``)
against their reference computations: closed-form 3x3 eigen-decomposition vs
``np.linalg.eigh``, voxel centroids with the range/subset selection done once vs Open3D
on the selected points, on constructed matrices and on a real KITTI scan."""

import numpy as np
import pytest

from flowslam.config import FlowRefinementConfig
from flowslam.datasets import open_dataset
from flowslam.sceneflow.refinement.static import (
    _covariances,
    _fitness,
    _near_any,
    _planar_points,
    _target_centroids,
    _voxel_centroids,
)
from flowslam.sceneflow.refinement.symmetric3 import smallest_eigenvectors, symmetric_eigenvalues


def _angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (deg) between the lines of unit vectors u and v (sign ignored), row by row."""
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", u, v)), 0.0, 1.0)))


@pytest.fixture(scope="module")
def kitti_target(kitti_extract):
    """Scan 4 of the KITTI extract, downsampled as the refinement does (0.4 m, 80 m)."""
    return _voxel_centroids(open_dataset(kitti_extract)[4].points, 0.4, 80.0)


def test_closed_form_eigen_matches_eigh_on_constructed_spectra():
    rng = np.random.default_rng(3)
    spectra = np.array([[1e-6, 0.5, 2.0], [0.0, 1.0, 1.0], [0.3, 0.3, 0.3], [1e-4, 1e-4, 5.0], [0.0, 0.0, 0.0],
                        [2.0, 3.0, 700.0]])
    q, _ = np.linalg.qr(rng.normal(size=(len(spectra), 3, 3)))
    cov = np.einsum("nij,nj,nkj->nik", q, spectra, q)
    values = symmetric_eigenvalues(cov)
    scale = np.maximum(spectra.sum(axis=1), 1e-12)
    # ~1e-15 of the trace for distinct eigenvalues; ~sqrt(eps) at a repeated one (the cubic's double root)
    assert np.all(np.abs(values - spectra) <= 1e-7 * scale[:, None])
    assert np.abs(values - spectra)[[0, 5]].max() <= 1e-12 * scale[5]
    vectors = smallest_eigenvectors(cov, values[:, 0])
    # a simple smallest eigenvalue (rows 0, 5): its eigenvector, up to sign, within 1e-6 deg
    assert np.all(_angle_deg(vectors[[0, 5]], q[[0, 5], :, 0]) < 1e-6)
    # a double smallest eigenvalue (row 3, a line): a unit vector of that plane, within 0.06 deg
    # (the eigenvalue is only good to ~sqrt(eps) there; eigh's vector is as arbitrary)
    assert abs(np.linalg.norm(vectors[3]) - 1) < 1e-12 and abs(vectors[3] @ q[3, :, 2]) < 1e-3
    # the zero matrix: no vector (NaN); a multiple of the identity (rounded): any unit vector
    assert np.isnan(vectors[4]).all()
    assert np.isnan(vectors[2]).all() or abs(np.linalg.norm(vectors[2]) - 1) < 1e-12


def test_closed_form_eigen_matches_eigh_on_real_neighbourhoods(kitti_target):
    c = FlowRefinementConfig()
    cov = _covariances(kitti_target, c.normal_radius_m)
    ref_values, ref_vectors = np.linalg.eigh(cov)
    values = symmetric_eigenvalues(cov)
    trace = values.sum(axis=1)
    assert np.max(np.abs(values - ref_values) / trace[:, None]) < 1e-8
    ref_planar = ref_values[:, 0] <= c.max_surface_variation * ref_values.sum(axis=1)
    planar = values[:, 0] <= c.max_surface_variation * trace
    assert ref_planar.sum() > 1000 and np.array_equal(planar, ref_planar)
    vectors = smallest_eigenvectors(cov[planar], values[planar, 0])
    gap = (ref_values[planar, 1] - ref_values[planar, 0]) / trace[planar]
    angle = _angle_deg(vectors, ref_vectors[planar, :, 0])
    well_posed = gap > 1e-3  # a defined normal: the two smallest eigenvalues apart
    assert well_posed.mean() > 0.95 and angle[well_posed].max() < 1e-4
    assert np.all(np.abs(np.linalg.norm(vectors, axis=1) - 1) < 1e-12)


def test_planar_points_match_the_eigh_selection(kitti_target):
    c = FlowRefinementConfig(line_radius_m=0.0)  # line-like points left out, not asked again
    planar, normals = _planar_points(kitti_target, c)
    ref_values, ref_vectors = np.linalg.eigh(_covariances(kitti_target, c.normal_radius_m))
    ref = ref_values[:, 0] <= c.max_surface_variation * ref_values.sum(axis=1)
    ref &= ref_values[:, 1] >= c.min_plane_spread * ref_values[:, 2]  # a plane, not a line
    assert 0 < c.min_plane_spread and ref.sum() > 1000
    np.testing.assert_array_equal(planar, kitti_target[ref])
    well_posed = (ref_values[ref, 1] - ref_values[ref, 0]) / ref_values[ref].sum(axis=1) > 1e-3
    assert _angle_deg(normals, ref_vectors[ref, :, 0])[well_posed].max() < 1e-4


def test_planar_points_with_lines_asked_again_match_scipys_neighbourhoods(kitti_target):
    """With line-like points asked again (``line_radius_m``, the default), the compiled
    neighbour search gives the planar points and normals of SciPy's query bit for bit."""
    from flowslam.sceneflow.refinement import static

    c = FlowRefinementConfig()
    planar, normals = _planar_points(kitti_target, c)
    original = static.knn_within
    static.knn_within = lambda *args: None  # decline: SciPy's query on the tree
    try:
        ref_planar, ref_normals = _planar_points(kitti_target, c)
    finally:
        static.knn_within = original
    flat, spread = static._flat_and_spread(symmetric_eigenvalues(_covariances(kitti_target, c.normal_radius_m)), c)
    assert c.line_radius_m > 0 and (flat & ~spread).sum() > 500 and len(planar) > 1000  # lines were asked again
    np.testing.assert_array_equal(planar, ref_planar)
    np.testing.assert_array_equal(normals, ref_normals)


@pytest.mark.parametrize("radius", [0.3, 0.6, 1.0])
def test_near_any_and_fitness_equal_the_kd_tree(kitti_target, radius):
    """The dynamic exclusion (``_near_any``) and the overlap (``_fitness``), compiled, give
    the KD-tree's answers on a real KITTI target: the same points near, the same share;
    a point at exactly the radius is not near (as in SciPy's query)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    others = kitti_target[::9] + rng.normal(scale=0.4, size=(len(kitti_target[::9]), 3))
    expected = np.isfinite(cKDTree(others).query(kitti_target, distance_upper_bound=radius)[0])
    got = _near_any(kitti_target, others, radius)
    assert 0.05 < expected.mean() < 0.95
    np.testing.assert_array_equal(got, expected)
    tree = cKDTree(kitti_target)
    moved = kitti_target[::5] + rng.normal(scale=0.5, size=(len(kitti_target[::5]), 3))
    share = np.isfinite(tree.query(moved, distance_upper_bound=radius)[0]).mean()
    assert _fitness(kitti_target, moved, radius) == share
    on_radius = np.array([[radius, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(_near_any(on_radius, np.zeros((1, 3)), radius), [False, True])


def test_target_centroids_are_open3ds(kitti_extract):
    """The target scan's compiled downsampling gives Open3D's centroids bit for bit, in
    voxel-key order (x, then y, then z) instead of Open3D's hash order."""
    scan = open_dataset(kitti_extract)[5].points
    c = FlowRefinementConfig()
    got = _target_centroids(scan, c.voxel_m, c.max_range_m)
    open3d = _voxel_centroids(scan, c.voxel_m, c.max_range_m)
    assert len(got) == len(open3d) > 10_000
    by_rows = lambda a: a[np.lexsort(a.T[::-1])]  # noqa: E731 -- rows sorted by x, then y, then z
    np.testing.assert_array_equal(by_rows(got), by_rows(open3d))
    keys = np.floor((got - got.min(axis=0) + c.voxel_m / 2) / c.voxel_m)
    assert np.all(np.diff(keys[:, 0]) >= 0)  # key order: x first


@pytest.mark.parametrize("far", [False, True])
def test_voxel_centroids_select_like_a_filtered_copy(far):
    """The range test and the subset in one selection give Open3D exactly the points a
    range-filtered copy of the subset would (so the voxel grid, which starts at the
    points' minimum, is the same)."""
    import open3d as o3d

    rng = np.random.default_rng(5)
    points = rng.uniform(-30, 30, size=(5000, 3))
    if far:
        points[:40] *= 5  # some beyond the 80 m range
    subset = rng.random(len(points)) < 0.8
    kept = points[subset & (np.linalg.norm(points, axis=1) < 80.0)]
    ref = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept)).voxel_down_sample(0.4).points)
    np.testing.assert_array_equal(_voxel_centroids(points, 0.4, 80.0, subset), ref)
    everything = points[np.linalg.norm(points, axis=1) < 80.0]
    ref_all = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(everything)).voxel_down_sample(0.4).points)
    np.testing.assert_array_equal(_voxel_centroids(points, 0.4, 80.0), ref_all)


@pytest.mark.parametrize("radius, max_nn", [(1.0, 20), (0.5, 20), (2.0, 40)])
def test_covariances_equal_open3d(kitti_target, radius, max_nn):
    """``_covariances`` (SciPy's query, compiled sums) gives Open3D's ``estimate_covariances``:
    the same neighbours in the same order, so the same sums, and the identity below 3
    neighbours (a few dozen isolated target points at 0.5 m)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kitti_target))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    expected = np.asarray(cloud.covariances)
    got = _covariances(kitti_target, radius, max_nn)
    identity = (expected == np.eye(3)).all(axis=(1, 2))
    assert identity.sum() > 0 and np.array_equal(identity, (got == np.eye(3)).all(axis=(1, 2)))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("radius, k", [(1.2, 20), (0.5, 20), (3.5, 40)])
def test_compiled_neighbours_equal_scipy_query(kitti_target, radius, k):
    """``knn_within`` (cubes of edge ``radius``) gives SciPy's ``cKDTree.query(k,
    distance_upper_bound)`` on a real KITTI target: the same neighbours in the same order,
    the same distances, N / inf where there are fewer than k; on every point and on a subset."""
    from scipy.spatial import cKDTree

    from flowslam.sceneflow.refinement.compiled_neighbourhoods import knn_within

    tree = cKDTree(kitti_target)
    for idx in (np.arange(len(kitti_target)), np.arange(3, len(kitti_target), 7)):
        dist, nb = tree.query(kitti_target[idx], k=k, distance_upper_bound=radius)
        got_nb, got_dist = knn_within(kitti_target, idx, radius, k)
        assert (nb == len(kitti_target)).any()  # some points have fewer than k within the radius
        np.testing.assert_array_equal(got_nb, nb)
        np.testing.assert_array_equal(got_dist, dist)


def test_compiled_neighbours_on_ties_and_edge_cases():
    """Equal distances come lowest index first; a point at exactly the radius is out (as
    in SciPy's query); more neighbours asked than points; non-finite points decline (None)."""
    from flowslam.sceneflow.refinement.compiled_neighbourhoods import knn_within

    points = np.array([[0.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, 0, 2.0]])
    nb, dist = knn_within(points, np.array([0]), 1.5, 10)
    assert nb.shape == (1, 5)
    np.testing.assert_array_equal(nb[0], [0, 1, 2, 3, 5])
    np.testing.assert_array_equal(dist[0], [0.0, 1.0, 1.0, 1.0, np.inf])
    nb, dist = knn_within(points, np.array([0]), 1.0, 3)  # the three at exactly 1.0 are not within
    np.testing.assert_array_equal(nb[0], [0, 5, 5])
    assert knn_within(np.array([[0.0, 0, 0], [np.nan, 0, 0]]), np.array([0]), 1.0, 2) is None
