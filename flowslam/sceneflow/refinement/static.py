"""Test-time refinement of the predicted static flow against the next scan (flow-guided ICP).

A learned flow is a good *guess* of where each point of scan ``k-1`` lands in scan
``k``, but its error (centimetres to decimetres per point, correlated by region) is
too large for odometry. The static part of the scene moves rigidly, so its flow can be
refined at test time against the geometry of scan ``k`` itself:

1. the static points of scan ``k-1`` (the network's mask) and the whole scan ``k``
   are voxel-downsampled; target points near where the network says a *dynamic*
   source point lands (``dynamic_exclusion_m``) are removed, so that moving objects
   pull neither way; only target points whose neighbourhood is a plane keep their
   normal and take part (``max_surface_variation``: tilted normals at curbs, the feet of
   walls and on cars, times the in-plane offsets of ring sampling, biased every step);
2. point-to-plane ICP (Open3D's rule with a Tukey kernel, compiled; coarse-to-fine
   correspondence distances) starts from the motion ``T_{k,k-1}`` registered from the
   network's static flow;
3. every downsampled static source point with a correspondence closer than the last
   stage's distance is *snapped*: its refined target is its position under the
   refined motion, moved onto the tangent plane of its nearest scan-``k`` point.

The result is a refined flow for a set of static points, (p, q - p) in the Argoverse
2 convention, which the shared :class:`flowslam.flow_odometry.FlowToPose` turns into
the odometry measurement as for any other flow. Registering the snapped pairs
(point-to-point) has the ICP solution as its stationary point: at the point-to-plane
optimum ``sum_i J_i^T n_i r_i = 0``, which is also the gradient of
``sum_i |T p_i - (T p_i - r_i n_i)|^2``. The residual spread of the pairs gives the
covariance.

Frames: source points in sensor frame ``k-1``, target points and ``p + flow`` in
sensor frame ``k``, ``T_curr_prev`` = ``T_{k,k-1}``; metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from flowslam.config.ssf import FlowRefinementConfig
from flowslam.geometry import transform_points
from flowslam.sceneflow.refinement.clusters import neighbourhood_covariances
from flowslam.sceneflow.refinement.compiled_icp import IcpTarget, nearest_within, register_point_to_plane
from flowslam.sceneflow.refinement.compiled_neighbourhoods import gathered_covariances, knn_within, within_any
from flowslam.sceneflow.refinement.symmetric3 import smallest_eigenvectors, symmetric_eigenvalues

__all__ = ["RefinedFlow", "refine_static_flow"]




@dataclass
class RefinedFlow:
    """Snapped static pairs: ``points`` (M,3) in frame k-1 and their refined ``flow`` (M,3).

    ``T_curr_prev``: the ICP motion ``T_{k,k-1}``; ``accepted``: False when the ICP
    was rejected (then ``points``/``flow`` are empty and the caller keeps its flow).
    ``target_points``: the downsampled scan k (M,3, frame k) without the points near
    predicted dynamic landings; the ICP used its planar part.
    """

    points: np.ndarray
    flow: np.ndarray
    T_curr_prev: np.ndarray
    accepted: bool
    target_points: np.ndarray
    stats: dict = field(default_factory=dict)
    scene_points: np.ndarray | None = None
    """The downsampled static points of scan k-1 (M,3, frame k-1), snapped or not: the
    scene whose geometry the odometry's degeneracy check judges."""


def _voxel_centroids(points: np.ndarray, voxel: float, max_range: float, subset: np.ndarray | None = None) -> np.ndarray:
    """Centroids (M,3) per ``voxel``-sized cube (Open3D's grid) of the points (N,3, sensor
    frame, m) closer than ``max_range`` to the sensor, of those in ``subset`` ((N,) bool)
    only when given; one selection copy at most, none when every point is kept."""
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    keep = np.einsum("ij,ij->i", p, p) < max_range * max_range
    if subset is not None:
        keep &= subset
    if not keep.all():
        p = np.compress(keep, p, axis=0)  # boolean indexing's rows, ~4x faster on a scan
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(p)))
    return np.asarray(cloud.voxel_down_sample(voxel).points)


def _target_centroids(points: np.ndarray, voxel: float, max_range: float) -> np.ndarray:
    """:func:`_voxel_centroids` of the target scan (no subset), compiled: the same voxels and
    centroids as Open3D's ``voxel_down_sample``, in voxel-key order
    (:func:`flowslam.compiled_voxels.open3d_voxel_means`). The target's order only decides
    between equally near points; the source keeps Open3D's order, on which its random
    subset depends."""
    from flowslam.compiled_voxels import open3d_voxel_means

    p = np.asarray(points, dtype=np.float64)
    return open3d_voxel_means(p, voxel, np.einsum("ij,ij->i", p, p) < max_range * max_range)[0]


def _near_any(points: np.ndarray, others: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: ``points`` (N,3) with one of ``others`` (M,3, same frame) closer than
    ``radius`` (m) (:func:`~flowslam.sceneflow.refinement.compiled_neighbourhoods.within_any`; KITTI 0-15
    replay: 8.8 -> 3.9 ms against SciPy's KD-tree; a step of its own for
    ``tools/bench_static_refinement.py``)."""
    return within_any(points, others, radius)


def _covariances(points: np.ndarray, radius: float, max_nn: int = 20, tree=None) -> np.ndarray:
    """(N,3,3) covariances (m^2) of the ``max_nn`` nearest neighbours within ``radius`` (m)
    of each point (N,3), itself included, and the identity below 3 neighbours: Open3D's
    ``estimate_covariances``, the same numbers (its search order and sums). The neighbours
    come from :func:`~flowslam.sceneflow.refinement.compiled_neighbourhoods.knn_within`
    (SciPy's query, the same arrays, from cubes of edge ``radius``; SciPy's query on
    ``tree``, a cKDTree over ``points`` built here when None, where that declines), the
    sums from one compiled pass per neighbourhood. On the 2-core VM, a KITTI target (13.5k
    points): the query 21 -> 13 ms; the sums 2 ms. Python's GIL is released while they run
    (Open3D holds it)."""
    cov, count = _gathered(points, np.arange(len(points)), radius, max_nn, tree)
    cov[count < 3] = np.eye(3)
    return cov


def _gathered(points: np.ndarray, idx: np.ndarray, radius: float, max_nn: int, tree=None) -> tuple:
    """((len(idx),3,3) covariances, (len(idx),) counts) of the at most ``max_nn`` neighbours
    within ``radius`` (m) of ``points[idx]``: compiled neighbour search
    (:func:`~flowslam.sceneflow.refinement.compiled_neighbourhoods.knn_within`), SciPy's on
    ``tree`` (built here when None) where that declines; the same neighbours either way."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    found = knn_within(points, idx, radius, max_nn)
    if found is None:
        tree = cKDTree(points) if tree is None else tree
        return neighbourhood_covariances(tree, points, idx, radius, max_nn)
    return gathered_covariances(points, *found)


LINE_NEIGHBOURS = 40
"""Neighbours (at most) of the wider neighbourhood of a line-like target point."""


def _flat_and_spread(values: np.ndarray, c: FlowRefinementConfig) -> tuple[np.ndarray, np.ndarray]:
    """(flat, spread), (N,) bool each, of neighbourhoods with ascending covariance
    eigenvalues ``values`` (N,3): surface variation at most ``max_surface_variation``; with
    ``min_plane_spread``, a middle eigenvalue at least that share of the largest (spread in
    two directions; all True without). A plane is both; flat but not spread is a line."""
    flat = values[:, 0] <= c.max_surface_variation * values.sum(axis=1)
    if c.min_plane_spread <= 0:
        return flat, np.ones(len(values), dtype=bool)
    return flat, values[:, 1] >= c.min_plane_spread * values[:, 2]


def _planar_points(points: np.ndarray, c: FlowRefinementConfig, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """The points (N,3, m) whose neighbourhood (``normal_radius_m``, at most 20 points) is a
    plane (:func:`_flat_and_spread`) and their unit normals (``tree``: a cKDTree over
    ``points`` for the searches the compiled one declines, built there when None). A
    neighbourhood that is flat but a line (one ring's stretch: ``min_plane_spread``) is
    asked again within ``line_radius_m`` (at most ``LINE_NEIGHBOURS`` points), and the
    point keeps that plane's normal when it is one.

    Leaving the non-planar points out removed most of the bias of the steps on simulated dt
    (pitch +0.0018 -> +0.0006 deg, x -0.78 -> -0.11 mm per step; docs/mapping.md); a line's
    smallest axis lies anywhere across it, and with range noise it tilts towards the
    radial direction (on a 32-beam sensor: a pitch every step, docs/sceneflow_evaluation.md,
    stop 35). Points with fewer than 3 neighbours get the identity covariance (as Open3D
    gives them): never planar."""
    cov = _covariances(points, c.normal_radius_m, tree=tree)
    values = symmetric_eigenvalues(cov)
    flat, spread = _flat_and_spread(values, c)
    planar = flat & spread
    line = np.flatnonzero(flat & ~spread)
    if line.size and c.line_radius_m > 0:  # one ring's stretch: ask a wider neighbourhood
        wide, count = _gathered(points, line, c.line_radius_m, LINE_NEIGHBOURS, tree)
        wide_values = symmetric_eigenvalues(wide)
        wide_flat, wide_spread = _flat_and_spread(wide_values, c)
        kept = wide_flat & wide_spread & (count >= 3)
        cov[line[kept]], values[line[kept]], planar[line[kept]] = wide[kept], wide_values[kept], True
    normals = smallest_eigenvectors(cov[planar], values[planar, 0])
    ok = np.isfinite(normals[:, 0])  # a zero covariance (coincident neighbours) has no normal
    return points[planar][ok], normals[ok]


def _icp(src_points: np.ndarray, target: IcpTarget, normals: np.ndarray, T_init: np.ndarray,
         c: FlowRefinementConfig) -> np.ndarray:
    """Point-to-plane ICP (Tukey kernel) of ``src_points`` (frame k-1) onto the planar
    target points (``target``, frame k) and their ``normals``, one stage per
    ``correspondence_m``, from ``T_init``; the refined ``T_{k,k-1}`` (4,4). Open3D's
    ``registration_icp`` rule with its convergence criteria as before (relative changes
    of 1e-6, the function's defaults), compiled
    (:func:`~flowslam.sceneflow.refinement.compiled_icp.register_point_to_plane`: one
    KD-tree for both stages and the snapping, Python's GIL released)."""
    return register_point_to_plane(src_points, target, normals, T_init, c.correspondence_m, c.max_iterations)


def _fitness(target: np.ndarray, x: np.ndarray, reach: float) -> float:
    """Share of the moved source points ``x`` (M,3, frame k) with a point of ``target``
    (N,3, frame k) closer than ``reach`` (m)
    (:func:`~flowslam.sceneflow.refinement.compiled_neighbourhoods.within_any`)."""
    return float(within_any(x, target, reach).mean())


def _snap(x: np.ndarray, target: IcpTarget, normals: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The moved source points ``x`` (M,3, frame k) with a planar target point (``target``,
    its unit ``normals``) within ``reach`` (m): (M,) bool, and their projections (K,3,
    frame k) onto its tangent plane."""
    j = nearest_within(target, x, reach)
    ok = j >= 0
    n = normals[j[ok]]
    d = np.einsum("ij,ij->i", x[ok] - target.points[j[ok]], n)
    return ok, x[ok] - d[:, None] * n


def refine_static_flow(
    source: np.ndarray,
    flow: np.ndarray,
    static_mask: np.ndarray,
    target: np.ndarray,
    T_init: np.ndarray,
    config: FlowRefinementConfig | None = None,
) -> RefinedFlow:
    """Refine the static flow of ``source`` (scan k-1, (N,3)) against ``target`` (scan k).

    ``flow`` (N,3) is the predicted flow (used only to place the dynamic points'
    landing spots), ``static_mask`` (N,) the predicted static points, ``T_init`` the
    motion ``T_{k,k-1}`` registered from the predicted static flow.
    """
    c = config or FlowRefinementConfig()
    static_mask = np.asarray(static_mask, dtype=bool)
    src_points = _voxel_centroids(source, c.voxel_m, c.max_range_m, static_mask)
    if len(src_points) > c.max_source_points:
        keep = np.random.default_rng(0).choice(len(src_points), c.max_source_points, replace=False)
        src_points = src_points[np.sort(keep)]
    tgt_points = _target_centroids(target, c.voxel_m, c.max_range_m)
    n_excluded = 0
    if c.dynamic_exclusion_m > 0 and not static_mask.all():
        landing = source[~static_mask] + flow[~static_mask]
        near = _near_any(tgt_points, landing, c.dynamic_exclusion_m)
        n_excluded = int(near.sum())
        tgt_points = tgt_points[~near]
    stats = {"refine_source_points": len(src_points), "refine_target_points": len(tgt_points),
             "refine_target_excluded": n_excluded}
    T_init = np.asarray(T_init, dtype=np.float64)
    empty = np.zeros((0, 3))
    if len(src_points) < 10 or len(tgt_points) < 10:
        return RefinedFlow(empty, empty, T_init.copy(), False, tgt_points, dict(stats, refine_reason="too few points"))
    planar, normals = _planar_points(tgt_points, c)  # ICP and snapping use these only
    stats["refine_target_not_planar"] = len(tgt_points) - len(planar)
    if len(planar) < 10:
        return RefinedFlow(empty, empty, T_init.copy(), False, tgt_points,
                           dict(stats, refine_reason="too few planar points"))
    planar_target = IcpTarget(planar)  # one KD-tree for the ICP's stages and the snapping
    T = _icp(src_points, planar_target, normals, T_init, c)

    # snap: refined position moved onto the tangent plane of the nearest target point
    p = src_points
    x = transform_points(T, p)
    reach = c.correspondence_m[-1]
    fitness = _fitness(tgt_points, x, reach)  # the overlap counts every surface, planar or not
    stats.update(refine_fitness=fitness, refine_correction_m=float(np.linalg.norm(T[:3, 3] - T_init[:3, 3])))
    if fitness < c.min_fitness:
        return RefinedFlow(empty, empty, T, False, tgt_points,
                           dict(stats, refine_reason=f"fitness {fitness:.2f} < {c.min_fitness}"))
    ok, q = _snap(x, planar_target, normals, reach)
    d = q - x[ok]
    stats["refine_plane_rmse_m"] = float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))
    return RefinedFlow(p[ok], q - p[ok], T, True, tgt_points, stats, p)
