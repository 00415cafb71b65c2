"""Far clusters need fewer points (``min_points_far`` from ``far_from_m``): a sensor's returns
thin out with range, and a far vehicle's pieces that an older scan sees through hold 8-14 points
on a 16-beam sensor. Hand-made point sets, real SciPy labelling and the real objects stage."""

import numpy as np

from flowslam.config.ssf import MotionEvidenceConfig, ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import bev_clusters, cluster_minimum
from flowslam.sceneflow.refinement.objects import refine_objects
from flowslam.sceneflow.refinement.visibility import _compact_clusters


def _blob(x: float, n: int) -> np.ndarray:
    """``n`` points 0.1 m apart along y at (``x``, 0..), 1 m above the sensor's ground (m)."""
    return np.column_stack([np.full(n, x), 0.1 * np.arange(n), np.full(n, -0.7)])


def test_the_minimum_follows_each_clusters_mean_range():
    xy = np.array([[10.0, 0.0], [10.0, 0.2], [29.0, 0.0], [31.0, 0.0], [40.0, 3.0], [40.0, -3.0]])
    labels = np.array([0, 0, 1, 1, 2, 3])
    counts = np.bincount(labels)
    # mean ranges: 10.0, 30.0 (at the boundary: far), 40.11, 40.11
    assert cluster_minimum(xy, labels, counts, 15, 8, 30.0).tolist() == [15, 8, 8, 8]
    assert cluster_minimum(xy, labels, counts, 15, 8, 35.0).tolist() == [15, 15, 8, 8]
    assert cluster_minimum(xy, labels, counts, 15, None, 30.0).tolist() == [15, 15, 15, 15]


def test_far_flags_of_a_few_points_pass_the_evidence_filter_near_ones_do_not():
    source = np.concatenate([_blob(10.0, 10), _blob(35.0, 10)])
    assert len(np.unique(bev_clusters(source, 0.4))) == 2
    idx = np.arange(len(source))
    off = _compact_clusters(source, idx, MotionEvidenceConfig())
    assert not off.any()
    on = _compact_clusters(source, idx, MotionEvidenceConfig(min_points_far=8))
    assert on.tolist() == [False] * 10 + [True] * 10
    assert not _compact_clusters(source, idx, MotionEvidenceConfig(min_points_far=11)).any()


def _registered(dynamic: np.ndarray, movers: np.ndarray, **options) -> list[int]:
    """Point counts of the objects the stage registered (its records) for a 10-point body at
    35 m on a static scan pair (scan k = scan k-1, no ego motion)."""
    source = _blob(35.0, 10)
    c = ObjectRefinementConfig(**options)
    result = refine_objects(source, np.zeros_like(source), dynamic, source.copy(), np.eye(4), 0.1, c, movers=movers)
    return [o["points"] for o in result.objects]


def test_a_far_cluster_of_a_few_geometric_movers_is_registered_the_networks_alone_is_not():
    every, none = np.ones(10, dtype=bool), np.zeros(10, dtype=bool)
    assert _registered(every, every) == []  # 15 points needed everywhere by default
    assert _registered(every, every, min_points_far=8) == [10]
    assert _registered(every, none, min_points_far=8) == []  # the network's candidates alone
    assert _registered(every, every, min_points_far=8, far_from_m=40.0) == []  # nearer than 40 m
