"""Test-time rigid refinement of the moving points' flow, object by object (first version).

After the ego motion ``T_{k,k-1}`` is refined (:mod:`flowslam.sceneflow.refinement.static`), the
*candidate* moving points of scan ``k-1`` -- the network's dynamic points, the movers of
the previous pair carried on (:class:`~flowslam.sceneflow.refinement.tracking.MoverPrior`) and the geometric movers
(:func:`flowslam.sceneflow.refinement.visibility.geometric_movers`) -- are grouped into objects by
connected components on a bird's-eye-view grid (``cluster_cell_m``). Each object with at least ``min_points``
points is registered to scan ``k`` by point-to-point ICP (Open3D, coarse-to-fine
correspondence distances), starting from the ego rotation and the median network
displacement of its points. Accepted objects (ICP fitness and RMSE within bounds)
get the rigid flow of their own motion -- or of the ego motion when that explains the
object's points about as well (fitness within ``static_preference``, RMSE within
``static_rmse_ratio``) or well enough (``static_fitness_accept``: structures that ICP can
slide along) -- and are labelled dynamic when that motion
moves their points faster than ``dynamic_speed_mps`` relative to the ego-motion flow,
static otherwise. Objects holding geometric movers also start ICP from the ego landing
shifted along their axis (``hypotheses_m``), and their movers get an ICP of their own
(a mover merged with static false positives keeps its own motion); each point then
takes the candidate motion that puts it nearest to scan ``k``'s surface, the ego motion
when that is strictly nearer. Points of rejected or too small objects keep the network's flow and
label, except that network-dynamic points whose ego-rigid landing spot lies on a
surface of scan ``k`` become static (the static explanation fits the data).

Instance tracking, object velocities over time and the iterative flow/segmentation
loop of SSF-PAN are a later step; this is the per-pair rigid refinement only.

Frames: source points in sensor frame ``k-1``, target points and ``p + flow`` in sensor
frame ``k``; metres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flowslam.geometry import transform_points
from flowslam.config.ssf import ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import bev_clusters

__all__ = ["ObjectRefinement", "refine_objects"]




@dataclass
class ObjectRefinement:
    """``flow`` (N,3) and ``dynamic`` (N,) bool for every source point after refinement;
    ``instance`` (N,) int: the point's entry in ``objects`` (-1: none); ``objects``: one
    dict per object tried (points, fitness, speed, accepted)."""

    flow: np.ndarray
    dynamic: np.ndarray
    instance: np.ndarray
    objects: list[dict] = field(default_factory=list)
    stats: dict = field(default_factory=dict)



def _register(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, c: ObjectRefinementConfig):
    """Point-to-point ICP of an object's points onto the target box; returns T.

    Point-to-point, not point-to-plane: normals of a few hundred sparse ring points are
    unreliable (measured: point-to-plane diverged on several simulated objects)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=c.max_iterations)
    for max_dist in c.correspondence_m:
        T = np.asarray(reg.registration_icp(s, t, max_dist, T, reg.TransformationEstimationPointToPoint(),
                                            criteria).transformation).copy()
    return T


def _normals_at(tree, tgt: np.ndarray, idx: np.ndarray, radius: float, k: int = 20) -> np.ndarray:
    """(len(idx),3) unit normals of target points ``idx``: smallest principal axis of their
    (at most ``k``) neighbours within ``radius`` (a point with < 3 neighbours gets NaN)."""
    dist, nb = tree.query(tgt[idx], k=min(k, len(tgt)), distance_upper_bound=radius)
    dist, nb = dist.reshape(len(idx), -1), nb.reshape(len(idx), -1)
    valid = np.isfinite(dist)
    pts = tgt[np.where(valid, nb, 0)] * valid[..., None]
    n = valid.sum(axis=1).astype(np.float64)
    mean = pts.sum(axis=1) / n[:, None]
    cov = np.einsum("mki,mkj->mij", pts, pts) / n[:, None, None] - np.einsum("mi,mj->mij", mean, mean)
    normals = np.linalg.eigh(cov)[1][:, :, 0]
    normals[n < 3] = np.nan
    return normals


def _best_icp(p: np.ndarray, tgt: np.ndarray, tree, starts: list[np.ndarray], c: "ObjectRefinementConfig"):
    """ICP of ``p`` onto ``tgt`` from each start; the best by (fitness, -RMSE):
    (T, fitness, rmse, start)."""
    best = None
    for T_start in starts:
        T = _register(p, tgt, T_start, c)
        fitness, rmse = _score(p, T, tree, tgt, c)
        if best is None or (fitness, -rmse) > (best[1], -best[2]):
            best = (T, fitness, rmse, T_start)
    return best


def _score(src: np.ndarray, T: np.ndarray, tree, tgt: np.ndarray, c: ObjectRefinementConfig):
    """(fitness, RMSE) of ``T src`` against the target surface: a point is an inlier when its
    nearest target point is within ``score_distance_m`` and it lies within ``score_plane_m``
    of that point's tangent plane; RMSE of the inliers' plane distances (m). Plane, not
    point, distances: a static surface seen by other rings in scan k is still a surface."""
    x = transform_points(T, src)
    dist, j = tree.query(x, distance_upper_bound=c.score_distance_m)
    ok = np.flatnonzero(np.isfinite(dist))
    if ok.size == 0:
        return 0.0, float("inf")
    normals = _normals_at(tree, tgt, j[ok], c.normal_radius_m)
    plane = np.abs(np.einsum("ij,ij->i", x[ok] - tgt[j[ok]], normals))
    inlier = plane < c.score_plane_m  # NaN normals compare False
    if not inlier.any():
        return 0.0, float("inf")
    return float(inlier.sum()) / len(src), float(np.sqrt(np.mean(plane[inlier] ** 2)))


def _principal_axis(points: np.ndarray) -> np.ndarray:
    """Unit principal axis (x, y, 0) of the BEV spread of (N,3) points."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    v = np.linalg.eigh(xy.T @ xy)[1][:, 1]
    return np.array([v[0], v[1], 0.0])



def refine_objects(
    source: np.ndarray,
    flow: np.ndarray,
    dynamic: np.ndarray,
    target: np.ndarray,
    T_ego: np.ndarray,
    dt: float,
    config: ObjectRefinementConfig | None = None,
    target_tree=None,
    movers: np.ndarray | None = None,
    seen_through: np.ndarray | None = None,
) -> ObjectRefinement:
    """Refine the flow of the candidate moving points of ``source`` (scan k-1) against
    ``target`` (scan k) given the ego motion ``T_ego`` = ``T_{k,k-1}`` (module doc).

    ``flow`` (N,3) is the network's flow, ``dynamic`` (N,) its labels, ``dt`` the scan
    interval (s). In the result, static points have the ego-rigid flow of ``T_ego``,
    registered objects their own rigid flow, other dynamic points the network's flow. ``target_tree``
    may be a ``scipy.spatial.cKDTree`` over (a downsampling of) ``target``. ``movers`` and
    ``seen_through`` (N,) bool: geometric motion evidence
    (:func:`flowslam.sceneflow.refinement.visibility.geometric_movers`); movers become candidates, and
    objects with seen-through points also start ICP from shifted ego landings
    (``hypotheses_m``), since free space says *that* they moved, not where to.
    """
    from scipy.spatial import cKDTree

    c = config or ObjectRefinementConfig()
    flow, dynamic = np.array(flow, dtype=np.float64), np.array(dynamic, dtype=bool)
    if target_tree is None:
        target_tree = cKDTree(target)
    near = np.hypot(source[:, 0], source[:, 1]) < c.max_range_m
    movers = np.zeros(len(source), dtype=bool) if movers is None else np.asarray(movers, dtype=bool)
    seen = np.zeros(len(source), dtype=bool) if seen_through is None else np.asarray(seen_through, dtype=bool)
    cand = np.flatnonzero((dynamic & near) | movers)
    labels = bev_clusters(source[cand], c.cluster_cell_m)
    counts = np.bincount(labels) if labels.size else np.zeros(0, dtype=np.int64)
    R = T_ego[:3, :3]
    interval = dt if dt and dt > 0 else 0.1
    speed_bound = c.dynamic_speed_mps * interval
    objects = []
    settled = np.zeros(len(source), dtype=bool)
    instance = np.full(len(source), -1, dtype=np.int64)
    near_target = target[np.hypot(target[:, 0], target[:, 1]) < c.max_range_m + c.margin_m + 5.0]
    near_target = near_target[np.argsort(near_target[:, 0], kind="stable")]  # x-sorted: boxes by bisection
    order = np.argsort(labels, kind="stable")  # candidates grouped by cluster
    starts = np.concatenate([[0], np.cumsum(counts)])
    for label in np.flatnonzero(counts >= c.min_points):
        idx = cand[order[starts[label]:starts[label + 1]]]
        p = source[idx]
        T0 = np.eye(4)
        T0[:3, :3] = R
        T0[:3, 3] = np.median(p + flow[idx] - p @ R.T, axis=0)  # the network's (or carried) displacement
        ego = transform_points(T_ego, p)  # where the points land if they are static
        sub = movers[idx]
        mover_starts = []
        if c.hypotheses_m and sub.sum() >= c.min_points and seen[idx].sum() >= c.min_seen_through:
            axis = R @ _principal_axis(p[sub])
            for d in c.hypotheses_m:
                shifted = T_ego.copy()
                shifted[:3, 3] += d * axis
                mover_starts.append(shifted)
        reach = max(abs(d) for d in c.hypotheses_m) if mover_starts else 0.0
        guess = transform_points(T0, p)
        lo = np.minimum(guess.min(axis=0), ego.min(axis=0)) - c.margin_m - reach
        hi = np.maximum(guess.max(axis=0), ego.max(axis=0)) + c.margin_m + reach
        a, b = np.searchsorted(near_target[:, 0], [lo[0], hi[0]])
        tgt = near_target[a:b]
        tgt = tgt[np.all((tgt[:, 1:] >= lo[1:]) & (tgt[:, 1:] <= hi[1:]), axis=1)]
        record = {"points": int(len(idx)), "target_points": int(len(tgt)), "accepted": False}
        instance[idx] = len(objects)
        objects.append(record)
        if len(tgt) < c.min_points:
            continue
        tree = cKDTree(tgt)
        static_fitness, static_rmse = _score(p, T_ego, tree, tgt, c)
        record.update(static_fitness=static_fitness, static_rmse_m=static_rmse)
        if static_fitness >= c.static_fitness_accept:  # static whatever the ICP finds: skip it
            record.update(accepted=True, speed_mps=0.0)
            flow[idx], dynamic[idx], settled[idx] = ego - p, False, True
            continue
        motions = []  # candidate rigid motions of (parts of) this object besides the ego motion
        T, fitness, rmse, T_start = _best_icp(p, tgt, tree, [T0] + mover_starts, c)
        moved_by = float(np.linalg.norm((T[:3, :3] - R) @ p.mean(axis=0) + T[:3, 3] - T_start[:3, 3]))
        record.update(fitness=fitness, rmse_m=rmse, icp_correction_m=moved_by)
        if fitness >= c.min_fitness and rmse <= c.max_rmse_m and moved_by <= c.max_correction_m:
            record["accepted"] = True
            if not (static_fitness >= fitness - c.static_preference
                    and static_rmse <= c.static_rmse_ratio * rmse + 0.005):
                motions.append(T)  # not explained as well by the ego motion
        if mover_starts:  # the geometric movers alone, from shifted ego landings
            Tm, fm, rm, _ = _best_icp(p[sub], tgt, tree, mover_starts + [T0], c)
            joint_on_movers = _score(p[sub], motions[0], tree, tgt, c)[0] if motions else 0.0
            record.update(mover_fitness=fm, mover_rmse_m=rm)
            # only when the object's own ICP does not already explain its movers
            if fm >= c.min_fitness and rm <= c.max_rmse_m and fm > joint_on_movers + c.static_preference:
                record["accepted"] = True
                motions.append(Tm)
        if not record["accepted"]:
            continue
        # per point: the ego motion when it puts the point strictly nearer to scan k's surface than
        # every object motion, else the nearest object motion (the first when none lands near)
        chosen = ego
        if motions:
            landings = [transform_points(M, p) for M in motions]
            dist = np.stack([tree.query(x, distance_upper_bound=c.score_distance_m)[0] for x in landings])
            best = np.argmin(dist, axis=0)
            chosen = np.stack(landings)[best, np.arange(len(idx))]
            d_ego = tree.query(ego, distance_upper_bound=c.score_distance_m)[0]
            chosen = np.where((d_ego < dist[best, np.arange(len(idx))])[:, None], ego, chosen)
        departure = np.linalg.norm(chosen - ego, axis=1)
        moving = departure > speed_bound
        record["speed_mps"] = float(np.median(departure[moving]) / interval) if moving.any() else 0.0
        flow[idx] = np.where(moving[:, None], chosen, ego) - p
        dynamic[idx] = moving
        settled[idx] = True
    # the rest of the network's dynamic points: static if the ego motion lands them on a surface
    rest = np.flatnonzero(dynamic & ~settled)
    on_surface = np.zeros(0, dtype=bool)
    if rest.size:
        rigid = transform_points(T_ego, source[rest])
        on_surface = np.isfinite(target_tree.query(rigid, distance_upper_bound=c.off_surface_m)[0])
        dynamic[rest[on_surface]] = False
    static = ~dynamic & ~settled
    flow[static] = transform_points(T_ego, source[static]) - source[static]
    stats = {
        "object_candidates": int(cand.size),
        "objects": len(objects),
        "objects_accepted": sum(o["accepted"] for o in objects),
        "objects_dynamic": sum(1 for o in objects if o.get("speed_mps", 0.0) > c.dynamic_speed_mps),
        "relabelled_static": int(on_surface.sum()),
    }
    return ObjectRefinement(flow, dynamic, instance, objects, stats)
