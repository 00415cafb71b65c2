"""Test-time rigid refinement of the moving points' flow, object by object (first version).

After the ego motion ``T_{k,k-1}`` is refined (:mod:`flowslam.sceneflow.refine`), the
*candidate* moving points of scan ``k-1`` (the network's dynamic points, plus points
whose network flow departs from the ego motion and whose rigid landing spot does not
lie on a surface of scan ``k``) are grouped into objects by connected components on a
bird's-eye-view grid (``cluster_cell_m``). Each object with at least ``min_points``
points is registered to scan ``k`` by point-to-point ICP (Open3D, coarse-to-fine
correspondence distances), starting from the ego rotation and the median network
displacement of its points. Accepted objects (ICP fitness and RMSE within bounds)
get the rigid flow of their own motion -- or of the ego motion when that explains the
object's points about as well (fitness within ``static_preference``, RMSE within
``static_rmse_ratio``) or well enough (``static_fitness_accept``: structures that ICP can
slide along) -- and are labelled dynamic when that motion
moves their points faster than ``dynamic_speed_mps`` relative to the ego-motion flow,
static otherwise. Points of rejected or too small objects keep the network's flow and
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
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["ObjectRefinementConfig", "ObjectRefinement", "MoverPrior", "above_ground", "bev_clusters", "refine_objects"]


class ObjectRefinementConfig(BaseModel):
    """Options of :func:`refine_objects` (metres, seconds)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    max_range_m: float = Field(50.0, gt=0)
    """Candidates farther than this (xy) are left as the network said."""
    departure_m: float = Field(0.0, ge=0)
    """A network-static point is a candidate when its flow departs this far from the ego flow
    (0: only the network's dynamic points are candidates; on the held-out simulation
    the extra candidates were mostly static points hidden in scan k) ..."""
    off_surface_m: float = Field(0.3, ge=0)
    """... and its ego-rigid landing spot is farther than this from every scan-k point."""
    cluster_cell_m: float = Field(0.6, gt=0)
    """BEV grid cell of the connected-component clustering (8-connected)."""
    min_points: int = Field(15, ge=3)
    correspondence_m: list[float] = Field(default_factory=lambda: [1.0, 0.3, 0.1])
    max_iterations: int = Field(15, ge=1)
    margin_m: float = Field(2.0, ge=0)
    """Target points within the box around both the object's predicted and its
    ego-rigid landing spots, grown by this, take part."""
    normal_radius_m: float = Field(1.0, gt=0)
    """Neighbourhood radius (at most 20 points) of the target normals used for scoring."""
    score_distance_m: float = Field(0.3, gt=0)
    score_plane_m: float = Field(0.1, gt=0)
    """A moved point is on the target surface when its nearest scan-k point is within
    ``score_distance_m`` and it is within ``score_plane_m`` of that point's tangent plane."""
    min_fitness: float = Field(0.6, ge=0, le=1)
    """Share of the object's points on the target surface after its ICP."""
    max_rmse_m: float = Field(0.12, gt=0)
    max_correction_m: float = Field(1.0, gt=0)
    """Objects whose ICP moved their centroid farther than this from the start are
    rejected: sparse clusters can lock onto a shifted copy of the ring pattern."""
    static_preference: float = Field(0.03, ge=0, le=1)
    """An object is static when the ego motion's fitness is within this of its own ICP's ..."""
    static_rmse_ratio: float = Field(1.2, ge=1)
    """... and its inlier RMSE at most this times the ICP's (+ 5 mm) ..."""
    static_fitness_accept: float = Field(0.9, ge=0, le=1.01)
    """... or when the ego motion alone puts this share of its points on scan k's surface:
    a planar patch (road, wall) fits equally well slid along itself, so a better ICP
    fitness there is no evidence of motion."""
    track_radius_m: float = Field(0.15, ge=0)
    """Points of the next scan this close to a mover's landing spot become candidates
    (``MoverPrior``; 0: no carry-over)."""
    dynamic_speed_mps: float = Field(0.5, ge=0)
    """Objects moving faster than this (relative to the ego-motion flow) are dynamic."""


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


def bev_clusters(points: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int label of 8-connected components of the occupied ``cell`` x ``cell`` BEV cells."""
    from scipy import ndimage

    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
    return labels[ij[:, 0], ij[:, 1]] - 1


def _candidates(source, flow, dynamic, target_tree, T_ego, c: ObjectRefinementConfig) -> np.ndarray:
    near = np.hypot(source[:, 0], source[:, 1]) < c.max_range_m
    if c.departure_m <= 0:
        return dynamic & near
    rigid = source @ T_ego[:3, :3].T + T_ego[:3, 3]
    departs = near & ~dynamic & (np.linalg.norm(source + flow - rigid, axis=1) > c.departure_m)
    idx = np.flatnonzero(departs)
    if idx.size:
        dist = target_tree.query(rigid[idx], distance_upper_bound=c.off_surface_m)[0]
        departs[idx[np.isfinite(dist)]] = False
    return (dynamic & near) | departs


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


def _score(src: np.ndarray, T: np.ndarray, tree, tgt: np.ndarray, c: ObjectRefinementConfig):
    """(fitness, RMSE) of ``T src`` against the target surface: a point is an inlier when its
    nearest target point is within ``score_distance_m`` and it lies within ``score_plane_m``
    of that point's tangent plane; RMSE of the inliers' plane distances (m). Plane, not
    point, distances: a static surface seen by other rings in scan k is still a surface."""
    x = src @ T[:3, :3].T + T[:3, 3]
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


def above_ground(points: np.ndarray, cell: float, clearance: float) -> np.ndarray:
    """(N,) bool: points higher than the lowest point of their ``cell`` x ``cell`` BEV cell
    plus ``clearance`` (m): a local ground estimate good enough to tell the road from what
    stands on it."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    _, inverse = np.unique(key, return_inverse=True)
    lowest = np.full(inverse.max() + 1, np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    return points[:, 2] > lowest[inverse] + clearance


def refine_objects(
    source: np.ndarray,
    flow: np.ndarray,
    dynamic: np.ndarray,
    target: np.ndarray,
    T_ego: np.ndarray,
    dt: float,
    config: ObjectRefinementConfig | None = None,
    target_tree=None,
) -> ObjectRefinement:
    """Refine the flow of the candidate moving points of ``source`` (scan k-1) against
    ``target`` (scan k) given the ego motion ``T_ego`` = ``T_{k,k-1}`` (module doc).

    ``flow`` (N,3) is the network's flow, ``dynamic`` (N,) its labels, ``dt`` the scan
    interval (s). In the result, static points have the ego-rigid flow of ``T_ego``,
    registered objects their own rigid flow, other dynamic points the network's flow. ``target_tree``
    may be a ``scipy.spatial.cKDTree`` over (a downsampling of) ``target``.
    """
    from scipy.spatial import cKDTree

    c = config or ObjectRefinementConfig()
    flow, dynamic = np.array(flow, dtype=np.float64), np.array(dynamic, dtype=bool)
    if target_tree is None:
        target_tree = cKDTree(target)
    cand = np.flatnonzero(_candidates(source, flow, dynamic, target_tree, T_ego, c))
    labels = bev_clusters(source[cand], c.cluster_cell_m)
    counts = np.bincount(labels) if labels.size else np.zeros(0, dtype=np.int64)
    R = T_ego[:3, :3]
    speed_bound = c.dynamic_speed_mps * (dt if dt and dt > 0 else 0.1)
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
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.median(p + flow[idx] - p @ R.T, axis=0)
        guess = p @ R.T + T[:3, 3]
        ego = p @ R.T + T_ego[:3, 3]  # where the points land if they are static
        lo = np.minimum(guess.min(axis=0), ego.min(axis=0)) - c.margin_m
        hi = np.maximum(guess.max(axis=0), ego.max(axis=0)) + c.margin_m
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
        T_start = T
        T = _register(p, tgt, T, c)
        fitness, rmse = _score(p, T, tree, tgt, c)
        record.update(fitness=fitness, rmse_m=rmse)
        moved_by = float(np.linalg.norm(T[:3, 3] + T[:3, :3] @ p.mean(axis=0) - T_start[:3, 3] - R @ p.mean(axis=0)))
        record["icp_correction_m"] = moved_by
        if fitness < c.min_fitness or rmse > c.max_rmse_m or moved_by > c.max_correction_m:
            continue
        if static_fitness >= fitness - c.static_preference and static_rmse <= c.static_rmse_ratio * rmse + 0.005:
            T = T_ego  # the ego motion explains the object as well as its own motion
        moved = p @ T[:3, :3].T + T[:3, 3]
        departure = float(np.median(np.linalg.norm(moved - ego, axis=1)))
        record.update(accepted=True, speed_mps=departure / (dt if dt and dt > 0 else 0.1))
        flow[idx] = moved - p
        dynamic[idx] = departure > speed_bound
        settled[idx] = True
    # the rest of the network's dynamic points: static if the ego motion lands them on a surface
    rest = np.flatnonzero(dynamic & ~settled)
    on_surface = np.zeros(0, dtype=bool)
    if rest.size:
        rigid = source[rest] @ R.T + T_ego[:3, 3]
        on_surface = np.isfinite(target_tree.query(rigid, distance_upper_bound=c.off_surface_m)[0])
        dynamic[rest[on_surface]] = False
    static = ~dynamic & ~settled
    flow[static] = source[static] @ R.T + T_ego[:3, 3] - source[static]
    stats = {
        "object_candidates": int(cand.size),
        "objects": len(objects),
        "objects_accepted": sum(o["accepted"] for o in objects),
        "objects_dynamic": sum(1 for o in objects if o["accepted"] and o["speed_mps"] > c.dynamic_speed_mps),
        "relabelled_static": int(on_surface.sum()),
    }
    return ObjectRefinement(flow, dynamic, instance, objects, stats)


class MoverPrior:
    """Carries the moving points of one scan pair over to the next (constant object velocity).

    After pair (k-1, k): the landing spots ``p + f`` (sensor frame k) of the points found
    dynamic, and each one's own motion ``m = p + f - T_{k,k-1} p`` (frame k, metres per
    scan interval). For pair (k, k+1) the points of scan k within ``radius_m`` of a
    landing spot become dynamic candidates with the predicted flow
    ``T_{k+1,k} p - p + R_{k+1,k} m`` (the ICP's start), so that an object found once
    keeps being refined even where the network misses it.
    """

    def __init__(self, radius_m: float = 0.15, ground_cell_m: float = 2.0, ground_clearance_m: float = 0.25):
        self.radius_m = radius_m
        self.ground_cell_m, self.ground_clearance_m = ground_cell_m, ground_clearance_m
        self._landing: np.ndarray | None = None
        self._motion: np.ndarray | None = None

    def update(self, source: np.ndarray, flow: np.ndarray, dynamic: np.ndarray, T_ego: np.ndarray) -> None:
        """Record pair (k-1, k): source points (frame k-1), flow, labels, ``T_ego`` = T_{k,k-1}.
        Ground-level points are not carried (``ground_clearance_m`` above the lowest point of
        their ``ground_cell_m`` BEV cell): the road under a mover would carry its motion on."""
        idx = np.flatnonzero(dynamic)
        if idx.size and self.ground_clearance_m > 0:
            near = np.hypot(source[:, 0], source[:, 1]) < np.hypot(*np.abs(source[idx, :2]).max(axis=0)) + 5.0
            above = np.zeros(len(source), dtype=bool)
            above[near] = above_ground(source[near], self.ground_cell_m, self.ground_clearance_m)
            idx = idx[above[idx]]
        p = source[idx]
        self._landing = p + flow[idx]
        self._motion = self._landing - (p @ T_ego[:3, :3].T + T_ego[:3, 3])

    def predict(self, points: np.ndarray, T_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) bool candidates among ``points`` (scan k, frame k) and their (N,3) predicted
        flow (rows of non-candidates are zero), given ``T_ego`` = T_{k+1,k}."""
        from scipy.spatial import cKDTree

        mask = np.zeros(len(points), dtype=bool)
        flow = np.zeros((len(points), 3))
        if self._landing is None or len(self._landing) == 0:
            return mask, flow
        lo, hi = self._landing.min(axis=0) - self.radius_m, self._landing.max(axis=0) + self.radius_m
        inside = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
        dist, j_in = cKDTree(self._landing).query(points[inside], distance_upper_bound=self.radius_m)
        mask[inside] = np.isfinite(dist)
        j = np.zeros(len(points), dtype=np.int64)
        j[inside] = np.minimum(j_in, len(self._landing) - 1)
        p = points[mask]
        flow[mask] = p @ T_ego[:3, :3].T + T_ego[:3, 3] - p + self._motion[j[mask]] @ T_ego[:3, :3].T
        return mask, flow

    def reset(self) -> None:
        self._landing = self._motion = None
