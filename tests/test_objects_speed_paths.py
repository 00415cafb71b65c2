"""The fast paths of the objects stage equal the straightforward computations they replace.

Each test builds a case (random clouds, a small street) and compares the shared/vectorised
helper with a direct numpy / SciPy version: KD-tree queries, ``np.minimum.at``, ``np.ptp``
per cluster, a box mask. Metres throughout.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flowslam.geometry import transform_points
from flowslam.sceneflow.refinement.clusters import (
    LocalGround,
    ScanSurface,
    above_ground,
    grid_occupancy,
    lowest_per_cell,
    plane_normals,
)
from flowslam.sceneflow.refinement.tracking import MoverPrior, object_evidence, small_instances
from flowslam.sceneflow.refinement.clusters import bev_extent


def _street(seed: int = 0, n: int = 20000) -> np.ndarray:
    """A road plane with noise, two walls and a box-shaped car (m, sensor frame)."""
    rng = np.random.default_rng(seed)
    road = np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), -1.7 + 0.03 * rng.standard_normal(n)])
    wall = np.column_stack([rng.uniform(-30, 30, n // 4), np.full(n // 4, 8.0) + 0.02 * rng.standard_normal(n // 4),
                            rng.uniform(-1.7, 3.0, n // 4)])
    car = np.column_stack([rng.uniform(4, 8, 2000), rng.uniform(-1, 1, 2000), rng.uniform(-1.3, -0.2, 2000)])
    return np.vstack([road, wall, car])


def test_lowest_per_cell_equals_minimum_at():
    rng = np.random.default_rng(1)
    for n_ids in (50, 40000):  # 16-bit radix path and the general path
        ids = rng.integers(0, n_ids, 5000)
        z = rng.normal(size=5000)
        expected = np.full(n_ids, np.inf)
        np.minimum.at(expected, ids, z)
        np.testing.assert_array_equal(lowest_per_cell(ids, z, n_ids), expected)


def test_local_ground_matches_the_per_subset_ground_and_voxel_alignment():
    from flowslam.mapping import voxel_ids

    points = _street(2)
    ground = LocalGround(points, 2.0)
    inverse, counts = voxel_ids(points * [1.0, 1.0, 0.0], 2.0)  # the straightforward cells
    lowest = np.full(len(counts), np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    np.testing.assert_array_equal(ground.above(0.3), points[:, 2] > lowest[inverse] + 0.3)
    np.testing.assert_array_equal(above_ground(points, 2.0, 0.25), ground.above(0.25))


def test_near_any_is_exact_against_a_kd_tree_query():
    rng = np.random.default_rng(3)
    scan = ScanSurface(_street(3), max_range_m=40.0)
    queries = _street(4, 8000)
    queries += rng.normal(scale=0.2, size=queries.shape)
    for radius in (0.1, 0.25, 0.6):
        expected = np.isfinite(cKDTree(scan.points).query(queries, distance_upper_bound=radius)[0])
        got = scan.near_any(queries, radius)
        np.testing.assert_array_equal(got, expected)
        assert 0 < got.sum() < len(got)  # both answers occur


def test_near_any_falls_back_to_the_tree_where_the_cubes_do_not_fit(monkeypatch):
    """Queries spanning more cubes than the packed keys count take the KD-tree path
    (``within_any``), with the same exact answer (the limit lowered here to force it); so do non-finite
    queries, which SciPy's tree refuses."""
    from flowslam.sceneflow.refinement import compiled_neighbourhoods

    scan = ScanSurface(_street(3), max_range_m=40.0)
    queries = _street(4, 3000)
    queries += np.random.default_rng(5).normal(scale=0.2, size=queries.shape)
    expected = np.isfinite(cKDTree(scan.points).query(queries, distance_upper_bound=0.25)[0])
    assert compiled_neighbourhoods.near_any_points(scan.points, queries, 0.25) is not None
    with_nan = np.vstack([queries, [[np.nan, 0.0, 0.0]]])
    assert compiled_neighbourhoods.near_any_points(scan.points, with_nan, 0.25) is None  # SciPy refuses them
    monkeypatch.setattr(compiled_neighbourhoods, "MAX_CELLS_PER_AXIS", 10)
    assert compiled_neighbourhoods.near_any_points(scan.points, queries, 0.25) is None
    np.testing.assert_array_equal(scan.near_any(queries, 0.25), expected)


@pytest.mark.parametrize("rounded", [False, True], ids=["street", "street-rounded-to-10cm"])
def test_scan_surface_box_query_equals_a_mask(rounded):
    """``in_box`` (compiled over the bucket index) gives the points inside the box in a
    deterministic order -- by x, equal x by their order in the scan -- which the objects'
    ICP sums depend on; rounded coordinates make many x equal."""
    points = _street(5)
    scan = ScanSurface(np.round(points, 1) if rounded else points, max_range_m=40.0)
    rng = np.random.default_rng(5)
    for _ in range(20):
        lo = rng.uniform(-45, 40, 3) * [1, 1, 0.1]
        hi = lo + rng.uniform(0, 15, 3)
        inside = np.flatnonzero(np.all((scan.points >= lo) & (scan.points <= hi), axis=1))
        expected = scan.points[inside[np.argsort(scan.points[inside, 0], kind="stable")]]
        np.testing.assert_array_equal(scan.in_box(lo, hi), expected)
    assert len(scan.in_box(np.array([100.0, 100, 0]), np.array([110.0, 110, 1]))) == 0  # outside the grid


def test_cached_normals_equal_fresh_normals():
    points = _street(6)
    scan = ScanSurface(points)
    tree = cKDTree(points)
    rng = np.random.default_rng(6)
    first, second = rng.integers(0, len(points), 300), rng.integers(0, len(points), 300)
    for idx in (first, second, np.concatenate([first, second])):  # the last one entirely from the cache
        got = scan.normals(idx, 1.0)
        expected = plane_normals(tree, points, idx, 1.0)
        # eigenvectors have a free sign: compare the lines
        np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", got, expected)), 1.0, atol=1e-9)


def test_dilated_grid_covers_every_point_within_one_voxel():
    rng = np.random.default_rng(7)
    spots = rng.uniform(-5, 5, (200, 3))
    cell = 0.15
    lo, hi = spots.min(axis=0) - cell, spots.max(axis=0) + cell
    shape = tuple(int(s) for s in np.floor((hi - lo) / cell) + 1)
    grid = grid_occupancy(spots, lo, cell, shape, dilate=True)
    queries = spots[rng.integers(0, 200, 5000)] + rng.uniform(-cell, cell, (5000, 3)) * 0.999
    ijk = np.floor((queries - lo) / cell).astype(np.int64)
    assert grid[np.ravel_multi_index(ijk.T, shape)].all()


@pytest.mark.parametrize("per_m, max_m", [(0.0, 0.0), (0.015, 0.45)])
def test_mover_prior_prediction_equals_a_plain_kd_tree_search(per_m, max_m):
    """Flat reach (0.15 m) and one that grows with the landing spot's range, against SciPy."""
    points = _street(8)
    rng = np.random.default_rng(8)
    T = np.eye(4)
    T[:3, 3] = [0.8, 0.02, 0.0]
    dynamic = rng.random(len(points)) < 0.05
    flow = transform_points(T, points) - points + rng.normal(scale=0.3, size=points.shape)
    prior = MoverPrior(0.15, radius_per_m=per_m, max_radius_m=max_m)
    prior.update(points, flow, dynamic, T)
    query = points + rng.normal(scale=0.1, size=points.shape)
    mask, predicted = prior.predict(query, T)
    landing = prior._landing
    dist, j = cKDTree(landing).query(query)
    ranges = np.hypot(landing[j, 0], landing[j, 1])
    expected = dist <= (np.clip(per_m * ranges, 0.15, max_m) if per_m else 0.15)
    np.testing.assert_array_equal(mask, expected)
    q = query[expected]
    np.testing.assert_allclose(predicted[expected],
                               transform_points(T, q) - q + prior._motion[j[expected]] @ T[:3, :3].T)
    assert not predicted[~expected].any()
    if per_m:
        assert (mask & (ranges > 20) & (dist > 0.15)).any()  # far points the flat 0.15 m reach would not take


def test_mover_prior_reach_by_hand():
    T = np.eye(4)
    landing = np.array([[5.0, 0.0, 0.5], [40.0, 0.0, 0.5]])
    prior = MoverPrior(0.15, ground_clearance_m=0.0, radius_per_m=0.01, max_radius_m=0.3)
    prior.update(landing, np.zeros_like(landing), np.ones(2, dtype=bool), T)
    query = landing + [0.0, 0.2, 0.0]  # 0.2 m off: beyond 0.15 m at 5 m, within the 0.3 m cap at 40 m (0.01 x 40 = 0.4)
    mask, _ = prior.predict(query, T)
    np.testing.assert_array_equal(mask, [False, True])
    mask, _ = prior.predict(landing + [0.0, 0.31, 0.0], T)
    assert not mask.any()


def test_small_instances_by_their_bev_box():
    points = np.array([[0.0, 0.0, 0.0], [0.6, 0.8, 2.0],  # instance 3: diagonal 1.0 m (height ignored)
                       [10.0, 0.0, 0.0], [13.0, 4.0, 0.0],  # instance 0: 5.0 m
                       [20.0, 0.0, 0.0]])  # no instance
    instance = np.array([3, 3, 0, 0, -1])
    np.testing.assert_array_equal(small_instances(points, instance, 1.0), [True, True, False, False, False])
    np.testing.assert_array_equal(small_instances(points, instance, 5.0), [True, True, True, True, False])
    assert not small_instances(points, np.full(5, -1), 9.0).any()


def test_mover_prior_grows_the_reach_of_small_objects_only():
    T = np.eye(4)
    # at 40 m: a walker (instance 0, 0.5 m wide) and a car (instance 1, 4.5 m wide); one unlabelled mover
    landing = np.array([[40.0, 0.0, 0.5], [40.0, 0.5, 0.5], [40.0, 10.0, 0.5], [44.0, 12.0, 0.5], [40.0, -10.0, 0.5]])
    instance = np.array([0, 0, 1, 1, -1])
    prior = MoverPrior(0.15, ground_clearance_m=0.0, radius_per_m=0.01, max_radius_m=0.3, grow_max_extent_m=1.0)
    prior.update(landing, np.zeros_like(landing), np.ones(5, dtype=bool), T, instance=instance)
    mask, _ = prior.predict(landing + [0.2, 0.0, 0.0], T)  # 0.2 m off: within the grown 0.3 m only
    np.testing.assert_array_equal(mask, [True, True, False, False, False])
    prior.update(landing, np.zeros_like(landing), np.ones(5, dtype=bool), T)  # no instances: all grow
    mask, _ = prior.predict(landing + [0.2, 0.0, 0.0], T)
    assert mask.all()


@pytest.mark.parametrize("shared", [False, True])
def test_mover_prior_with_a_shared_ground_keeps_the_same_movers(shared):
    points = _street(9)
    T = np.eye(4)
    dynamic = np.zeros(len(points), dtype=bool)
    dynamic[-2000:] = True  # the car ...
    dynamic[:500] = True  # ... and some road under it, which must not be carried
    prior = MoverPrior(0.15)
    prior.update(points, np.zeros_like(points), dynamic, T, LocalGround(points, 2.0) if shared else None)
    assert len(prior._landing) == 2000


def test_bev_extent_equals_ptp_per_label():
    rng = np.random.default_rng(10)
    xy = rng.uniform(-20, 20, (3000, 2))
    labels = rng.integers(0, 40, 3000)
    got = bev_extent(xy, labels, 40)
    expected = [np.hypot(*np.ptp(xy[labels == k], axis=0)) for k in range(40)]
    np.testing.assert_allclose(got, expected)


def test_in_bounds_equals_the_all_axes_test_including_points_on_the_bounds():
    from flowslam.sceneflow.refinement.clusters import in_bounds

    rng = np.random.default_rng(4)
    lo, hi = np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 0.5])
    points = rng.uniform(-3, 3, (5000, 3))
    points[:10] = lo  # exactly on a corner: inside
    points[10:20] = hi
    points[20:30] = np.nextafter(hi, np.inf)  # just beyond: outside
    expected = np.all((points >= lo) & (points <= hi), axis=1)
    assert np.array_equal(in_bounds(points, lo, hi), expected)
    assert expected[:20].all() and not expected[20:30].any() and 0 < expected.sum() < len(points)


def test_gathered_covariances_equal_numpy_per_neighbourhood():
    """``neighbourhood_covariances`` (compiled sums) equals ``np.cov`` (population) of each
    point's neighbours within the radius, at most k of them, the point itself included."""
    from flowslam.sceneflow.refinement.clusters import neighbourhood_covariances

    points = _street(7, 4000)
    tree = cKDTree(points)
    idx = np.random.default_rng(8).choice(len(points), 300, replace=False)
    cov, count = neighbourhood_covariances(tree, points, idx, 0.8, k=12)
    for row, i in enumerate(idx):
        dist, nb = tree.query(points[i], k=12, distance_upper_bound=0.8)
        near = points[nb[np.isfinite(dist)]]
        assert count[row] == len(near) >= 1
        np.testing.assert_allclose(cov[row], np.cov(near.T, bias=True).reshape(3, 3), atol=1e-12)


@pytest.mark.parametrize("radius, k", [(1.0, 20), (0.3, 20), (2.0, 4)])
def test_compiled_normals_equal_the_numpy_closed_forms(radius, k):
    """``plane_normals`` (one compiled pass per neighbourhood) gives the normals of the NumPy
    closed forms (``symmetric3``) on the covariances of the same neighbourhoods: NaN on the
    same points (fewer than 3 neighbours, or none at all), else the same unit vector to
    1e-12 (the compiled ``arccos`` and ``cos`` may round the last bit differently)."""
    from flowslam.sceneflow.refinement.clusters import neighbourhood_covariances
    from flowslam.sceneflow.refinement.symmetric3 import smallest_eigenvectors, symmetric_eigenvalues

    rng = np.random.default_rng(9)
    points = np.vstack([_street(9, 6000), rng.uniform(-60, 60, (40, 3))])  # and some isolated points
    tree = cKDTree(points)
    idx = rng.choice(len(points), 2000, replace=False)
    cov, count = neighbourhood_covariances(tree, points, idx, radius, k)
    expected = smallest_eigenvectors(cov, symmetric_eigenvalues(cov)[:, 0])
    expected[count < 3] = np.nan
    got = plane_normals(tree, points, idx, radius, k)
    missing = np.isnan(expected).any(axis=1)
    assert 0 < missing.sum() < len(idx) and np.array_equal(np.isnan(got).any(axis=1), missing)
    np.testing.assert_allclose(got[~missing], expected[~missing], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(got[~missing], axis=1), 1.0, atol=1e-12)


def test_ego_landings_asked_once_equal_the_per_object_queries():
    """The round's cache of ego-landing distances (``_EgoLandings``), filled by one query of
    all the objects' points as ``_registered`` does, gives every object's points the
    numbers a query of that object alone gives (point and plane distances, bit for bit),
    asks scan k only for points it has not seen, and the static scores built on it
    (:func:`_fit` of its plane distances) equal :func:`_score` under the ego motion one
    object at a time."""
    from flowslam.config import ObjectRefinementConfig
    from flowslam.sceneflow.refinement import objects

    c = ObjectRefinementConfig()
    source = _street(4)
    T_ego = np.eye(4)
    T_ego[:3, :3] = [[np.cos(0.02), -np.sin(0.02), 0.0], [np.sin(0.02), np.cos(0.02), 0.0], [0.0, 0.0, 1.0]]
    T_ego[:3, 3] = [0.9, 0.05, 0.01]
    surface = ScanSurface(transform_points(T_ego, source[::2]) + 0.01, max_range_m=40.0)
    rng = np.random.default_rng(5)
    groups = [np.sort(rng.choice(len(source), n, replace=False)) for n in (40, 700, 3000)]
    cache = objects._EgoLandings(source, T_ego, surface, c)
    cache(np.concatenate(groups))
    for idx in groups:
        dist, plane = objects._surface_distances(transform_points(T_ego, source[idx]), surface, c)
        cached = cache(idx)
        np.testing.assert_array_equal(cached[0], dist)
        np.testing.assert_array_equal(cached[1], plane)
        assert objects._fit(cached[1], c) == objects._score(source[idx], T_ego, surface, c)
        assert np.isfinite(dist).any() and np.isinf(dist).any()  # the case has both
    asked = cache.known.copy()
    cache(groups[1][:100])
    np.testing.assert_array_equal(cache.known, asked)  # nothing asked twice


def _joined_by_pairs(xy: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """The straightforward joining: every pair of points within ``gap`` (SciPy), a graph of
    the labels they connect, its connected components."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(xy).query_pairs(gap, output_type="ndarray")
    a, b = labels[pairs[:, 0]], labels[pairs[:, 1]]
    n = int(labels.max()) + 1
    graph = coo_matrix((np.ones(np.count_nonzero(a != b)), (a[a != b], b[a != b])), shape=(n, n))
    return connected_components(graph, directed=False)[1][labels]


def test_joined_labels_equal_the_components_of_the_pairs_within_the_gap():
    from flowslam.sceneflow.refinement.clusters import bev_clusters
    from flowslam.sceneflow.refinement.compiled_neighbourhoods import joined_labels

    rng = np.random.default_rng(11)
    for _ in range(60):  # scattered clouds of varied density and shape, and a street
        p = rng.uniform(-5, 5, (int(rng.integers(2, 2500)), 3)) * rng.uniform(0.2, 3, 3)
        labels = bev_clusters(p, 0.3)
        gap = float(rng.uniform(0.31, 1.0))
        np.testing.assert_array_equal(joined_labels(p[:, :2], labels, gap), _joined_by_pairs(p[:, :2], labels, gap))
    street = _street(12, 6000)
    labels = bev_clusters(street, 0.3)
    xy = street[:, :2]
    np.testing.assert_array_equal(joined_labels(xy, labels, 0.8), _joined_by_pairs(xy, labels, 0.8))
    # two points exactly the gap apart are joined (query_pairs' "at most r"); a hair farther, not
    xy = np.array([[0.0, 0.0], [0.5, 0.0], [1.5, 0.0]])
    assert list(joined_labels(xy, np.array([0, 1, 2]), 0.5)) == [0, 0, 1]
    assert list(joined_labels(xy, np.array([2, 1, 0]), 1.0)) == [0, 0, 0]
    with pytest.raises(ValueError):
        joined_labels(np.array([[0.0, 0.0], [np.nan, 0.0]]), np.array([0, 1]), 0.5)


def test_object_evidence_counts_flags_per_instance():
    flags = np.array([1, 0, 0, 0, 1, 1, 0], dtype=bool)
    instance = np.array([0, 0, 0, 1, 1, -1, -1])
    # instance 0: 1 of 3 flagged; instance 1: 1 of 2; the unlabelled points stand for themselves
    np.testing.assert_array_equal(object_evidence(flags, instance, 1, 0.4), [0, 0, 0, 1, 1, 1, 0])
    np.testing.assert_array_equal(object_evidence(flags, instance, 2, 0.0), [0, 0, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(object_evidence(flags, instance, 1, 0.3), [1, 1, 1, 1, 1, 1, 0])


def test_mover_prior_stops_carrying_an_object_after_its_quiet_pairs():
    """A walker (instance 0) moving 0.1 m per scan along x, found with evidence once: it is
    carried for ``max_quiet_pairs`` pairs without evidence, then no more; evidence of any
    share of it (here through a point it grew by) starts the count again."""
    T = np.eye(4)
    step = np.array([0.1, 0.0, 0.0])
    body = np.array([[10.0, 0.0, 0.5], [10.0, 0.2, 0.5], [10.0, 0.4, 0.9]])
    prior = MoverPrior(0.15, ground_clearance_m=0.0, max_quiet_pairs=2)
    instance = np.zeros(3, dtype=np.int64)
    flow = np.tile(step, (3, 1))

    def carried(points, shown):
        mask, _ = prior.predict(points, T)
        prior.update(points, flow, mask, T, instance=instance, evidence=shown)
        return mask

    prior.update(body, flow, np.ones(3, dtype=bool), T, instance=instance, evidence=np.ones(3, dtype=bool))
    quiet = np.zeros(3, dtype=bool)
    assert carried(body + step, quiet).all()  # quiet pair 1
    assert carried(body + 2 * step, quiet).all()  # quiet pair 2
    assert not carried(body + 3 * step, quiet).any()  # the limit: dropped
    # again, with one point showing motion in the second pair: the whole object starts over
    prior.update(body, flow, np.ones(3, dtype=bool), T, instance=instance, evidence=np.ones(3, dtype=bool))
    assert carried(body + step, quiet).all()
    assert carried(body + 2 * step, object_evidence(np.array([False, False, True]), instance, 1, 0.0)).all()
    assert carried(body + 3 * step, quiet).all()
    assert carried(body + 4 * step, quiet).all()
    assert not carried(body + 5 * step, quiet).any()
    # without a limit, or with one for objects wider than the walker (0.4 m), it is carried on
    for prior in (MoverPrior(0.15, ground_clearance_m=0.0),
                  MoverPrior(0.15, ground_clearance_m=0.0, max_quiet_pairs=1, quiet_min_extent_m=0.5)):
        prior.update(body, flow, np.ones(3, dtype=bool), T, instance=instance, evidence=quiet)
        assert all(carried(body + (k + 1) * step, quiet).all() for k in range(5))
    prior = MoverPrior(0.15, ground_clearance_m=0.0, max_quiet_pairs=1, quiet_min_extent_m=0.3)  # wider: limited
    prior.update(body, flow, np.ones(3, dtype=bool), T, instance=instance, evidence=quiet)
    assert carried(body + step, quiet).all() and not carried(body + 2 * step, quiet).any()
