"""Test-time rigid refinement of the moving points' flow, object by object (first version).

After the ego motion ``T_{k,k-1}`` is refined (:mod:`flowslam.sceneflow.refinement.static`), the
*candidate* moving points of scan ``k-1`` -- the network's dynamic points, the movers of
the previous pair carried on (:class:`~flowslam.sceneflow.refinement.tracking.MoverPrior`) and the geometric movers
(:func:`flowslam.sceneflow.refinement.visibility.geometric_movers`) -- are grouped into objects by
connected components on a bird's-eye-view grid (``cluster_cell_m``); points nearer than
``min_range_m`` (the ego vehicle's own body) are never candidates, and a cluster with
fewer than ``min_above_ground_points`` points above the local ground is road (static, no
ICP: a ring's arc on flat ground slides along itself under ICP). A cluster wider than
``split_extent_m`` is also registered as its ``instance_cell_m`` components, which replace it
when they explain ``split_gain`` more of it (a queue or a crowd merged into one cluster).
Each object with at least ``min_points`` points is registered to scan ``k`` by
point-to-point ICP (Open3D's rule, compiled: :mod:`~flowslam.sceneflow.refinement.compiled_icp`;
coarse-to-fine correspondence distances), starting from the ego rotation and the median
network displacement of its points. Accepted objects (ICP fitness and RMSE within bounds)
get the rigid flow of their own motion (polished by one point-to-plane ICP,
``plane_stage_radius_m``, kept when it fits as tightly, and made planar,
``planar_motion``; of several ICP starts the first, the network's or the track's
displacement, keeps its result unless another fits clearly better,
``prefer_first_start``) -- or of the ego motion when that explains the
object's points about as well (fitness within ``static_preference``, RMSE within
``static_rmse_ratio``; the fitness margin is at least ``static_preference_sigmas`` standard
errors of a share of the object's points) or well enough (``static_fitness_accept``:
structures that ICP can slide along) -- and are labelled dynamic when that motion
moves their points faster than ``dynamic_speed_mps`` relative to the ego-motion flow
(horizontally, ``horizontal_departure``: objects move on the ground), static otherwise. Objects holding geometric movers also start ICP from the ego landing
shifted along their axis (``hypotheses_m``), and their movers get an ICP of their own
(a mover merged with static false positives keeps its own motion); each point then
takes the candidate motion that puts it nearest to scan ``k``'s surface, the ego motion
when that is strictly nearer (unless its ego landing lies on the object's own new
surface, ``own_surface_m``). A moving object whose points lie inside a larger body (most
of them have other points clear of the ground within ``EMBED_RADIUS_M``) stays static
when the ego motion explains that body better than the object's motion
(``embedded_share``): its ICP slid a flagged part of a static body. Points of rejected or
too small objects keep the network's flow and label, except that network-dynamic points
whose ego-rigid landing spot lies on a surface of scan ``k`` become static (the static
explanation fits the data), and so do the groups of the rest (an object not accepted, else a
BEV cluster) that their own flow moves at most ``rest_min_speed_mps`` and that hold no
geometric mover or seen-through point (:func:`_slow_rest`).

Scan k is indexed once per pair (:class:`~flowslam.sceneflow.refinement.clusters.ScanSurface`):
the ICP boxes come from its BEV buckets (same points, same x order as a bisection of the
x-sorted scan), and every score and landing test queries its one cube index, with each
target normal computed once. The box only bounds the ICP's target; scores look at the
whole scan. The scored points start >= ``margin_m`` inside the box, so a score differs
from a box-only one only where a motion puts them near the box's edge (target normals
there then see their neighbours outside the box too); no output changed on the KITTI
and simulated rush-hour pairs replayed against the box-only version.

:func:`refine_objects` repeats the refinement (SSF-PAN's flow <->
segmentation loop, ``iterations``): each round clusters the points the previous round
left dynamic (the static false positives it split off no longer pull on an object's
ICP), starts each object's ICP from the flow the previous round gave it, and relabels,
until a round changes at most ``converged_share`` of the labels of the points dynamic in
either round, and the flow of those dynamic in both by at most ``converged_flow_m`` on
average. The ego motion stays fixed: it is the odometry measurement,
final before this stage runs. Instance tracking over time lives in
:mod:`flowslam.object_tracks`.

Frames: source points in sensor frame ``k-1``, target points and ``p + flow`` in sensor
frame ``k``; metres, seconds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flowslam.geometry import rigid_flow, transform_points
from flowslam.config.ssf import ObjectRefinementConfig
from flowslam.sceneflow.refinement.compiled_icp import IcpTarget, register, register_point_to_plane
from flowslam.sceneflow.refinement.compiled_neighbourhoods import joined_labels, within_any
from flowslam.sceneflow.refinement.clusters import (
    ScanSurface,
    bev_clusters,
    bev_extent,
    cluster_minimum,
    in_bounds,
    lowest_per_cell,
    ring_count,
)
from flowslam.sceneflow.refinement.slide import OlderView, slide_motion
from flowslam.sceneflow.refinement.visibility import baseline_window_margins

__all__ = ["ObjectRefinement", "hold_tracks", "refine_objects", "release_instance", "release_tracks"]




@dataclass
class ObjectRefinement:
    """``flow`` (N,3) and ``dynamic`` (N,) bool for every source point after refinement;
    ``instance`` (N,) int: the point's entry in ``objects`` (-1: none); ``objects``: one
    dict per object tried (points, fitness, speed, accepted), per further instance of a
    moving object (``part_of``), per held track (``held``) and per instance of dynamic
    points that no accepted object holds (``unregistered``)."""

    flow: np.ndarray
    dynamic: np.ndarray
    instance: np.ndarray
    objects: list[dict] = field(default_factory=list)
    stats: dict = field(default_factory=dict)



def _register(p: np.ndarray, target: IcpTarget, T: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray | None:
    """Point-to-point ICP of an object's points ``p`` onto ``target`` (its box's
    :class:`~flowslam.sceneflow.refinement.compiled_icp.IcpTarget`, one KD-tree shared by
    every start) from ``T``, coarse to fine (``correspondence_m``, each stage at most
    ``max_iterations``; Open3D's point-to-point rule, compiled); returns T.

    Point-to-point, not point-to-plane: normals of a few hundred sparse ring points are
    unreliable (measured: point-to-plane diverged on several simulated objects, and as a
    last stage of every start it let wrong starts win on the real AV2 pair). See
    :func:`_polish` for the one point-to-plane step that is used.

    None when an iteration turns the object farther than ``max_turn_rad`` (> 0) from the
    start's rotation (given up)."""
    return register(p, target, T, c.correspondence_m, c.max_iterations, ICP_RELATIVE_CHANGE, ICP_RELATIVE_CHANGE,
                    max_turn_rad=c.max_turn_rad or None)


def _near_landing(box: np.ndarray, p: np.ndarray, T: np.ndarray, max_dist: float) -> np.ndarray:
    """The target points of ``box`` within ``max_dist`` + ``FINE_STAGE_SLACK_M`` of the
    bounding box of ``T p``."""
    landing = transform_points(T, p)
    reach = max_dist + FINE_STAGE_SLACK_M
    return box[in_bounds(box, landing.min(axis=0) - reach, landing.max(axis=0) + reach)]


def _polish(p: np.ndarray, box: np.ndarray, T: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray | None:
    """One point-to-plane ICP of ``p`` from ``T`` at the finest correspondence distance, on
    the normals of the target points near its landing (Open3D's ``estimate_normals``: the
    smallest axis of their 20 nearest neighbours within ``plane_stage_radius_m``, each
    point on its own, spread over the cores); None when too few target points.
    Point-to-point converges slowly along the faces an object slides on (its sides pull
    nothing, so each step moves it by the share of its front and back faces);
    point-to-plane finishes that slide. The ICP is Open3D's point-to-plane rule without a
    kernel, compiled (:func:`~flowslam.sceneflow.refinement.compiled_icp.register_point_to_plane`):
    its sums run in the source's order, where the per-thread sums of Open3D's
    ``registration_icp`` made the objects of a sequence differ from one run to the next
    (stop 57)."""
    import open3d as o3d

    near = _near_landing(box, p, T, c.correspondence_m[-1])
    if len(near) < PLANE_STAGE_MIN_TARGET:
        return None
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(near))
    target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=c.plane_stage_radius_m, max_nn=20))
    normals = np.asarray(target.normals)
    return register_point_to_plane(p, IcpTarget(near), normals, T, [c.correspondence_m[-1]], c.max_iterations,
                                   ICP_RELATIVE_CHANGE, ICP_RELATIVE_CHANGE, kernel=np.inf)


ICP_RELATIVE_CHANGE = 1e-6
"""An object ICP stage stops when its fitness and inlier RMSE (m) each change by less."""


SAME_SOLUTION_M = 0.03
"""Two ICP results whose landings of an object differ by at most this on average (m) are
one solution (:func:`_best_icp`)."""

PLANE_STAGE_MIN_TARGET = 10
"""Target points the point-to-plane stage needs (fewer: it is skipped)."""

FINE_STAGE_SLACK_M = 0.5
"""How far (m) the point-to-plane polish may move an object beyond its correspondence
distance and still see every target point it could match (:func:`_polish`)."""


def _best_icp(p: np.ndarray, tgt: IcpTarget, surface: ScanSurface, starts: list[np.ndarray],
              T_ego: np.ndarray, c: ObjectRefinementConfig, prefer_first: bool = False):
    """ICP of ``p`` onto the target box ``tgt`` from each start;
    the best (:func:`_pick`, ``prefer_first``) by fitness and RMSE against ``surface`` of the
    results that keep the object's centroid on the ground (not :func:`_lifted` from its
    ``T_ego`` landing) and were not given up for turning (``max_turn_rad``): (T, fitness,
    rmse, start). When there is none: (the first start, 0, inf, the first start).

    With ``prefer_first``, a first result whose fitness is within :func:`_fitness_margin` of
    1 is kept without registering the other starts: none can then beat it by that margin,
    so :func:`_pick` would keep it or another result that lands within ``SAME_SOLUTION_M``
    of it (the same solution)."""
    results = []
    centroid = p.mean(axis=0)
    for i, T_start in enumerate(starts):
        T = _register(p, tgt, T_start, c)
        if T is None or _lifts_centroid(T, centroid, T_ego, c):
            continue
        results.append((T, *_score(p, T, surface, c), T_start))
        if prefer_first and i == 0 and results[0][1] + _fitness_margin(results[0][1], len(p), c) >= 1.0:
            return results[0]
    if not results:
        return starts[0], 0.0, float("inf"), starts[0]
    return _pick(results, p, prefer_first and results[0][3] is starts[0], c)


def _pick(results: list[tuple], p: np.ndarray, prefer_first: bool, c: ObjectRefinementConfig) -> tuple:
    """The best of an object's ICP ``results`` ((T, fitness, rmse, start), in the order of
    their starts; ``p``: the registered points, frame k-1) by (fitness, -RMSE); with
    ``prefer_first``, the first result instead when the best one has at most
    :func:`_fitness_margin` more fitness and lands ``p`` elsewhere (by more than
    ``SAME_SOLUTION_M`` on average): a vehicle sliding along its own side fits scan k about
    as well anywhere along the slide, and the first start (the network's or the track's
    displacement) is the better guess there."""
    best = max(results, key=lambda r: (r[1], -r[2]))
    first = results[0]
    if not prefer_first or best is first or best[1] > first[1] + _fitness_margin(first[1], len(p), c):
        return best
    apart = np.linalg.norm(transform_points(best[0], p) - transform_points(first[0], p), axis=1).mean()
    return first if apart > SAME_SOLUTION_M else best


def _polished(q: np.ndarray, box: np.ndarray, T: np.ndarray, fitness: float, rmse: float, surface: ScanSurface,
              T_ego: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray:
    """A moving object's motion ``T`` (of its ICP points ``q``; ``fitness``, ``rmse``: its
    :func:`_score`) after :func:`_polish` with ``plane_stage_radius_m`` > 0 (made
    :func:`_planar` with ``planar_motion``), when the polish keeps the object on the ground
    and :func:`_keeps_polish` accepts its fit (a few points more or less within
    ``score_plane_m`` is noise, and point-to-point ICP leaves a slide short while fitting
    as many points); else ``T``. Only the motions kept as an object's own are polished (on
    real KITTI most objects are static)."""
    if c.plane_stage_radius_m <= 0 or len(q) < c.plane_stage_min_points:
        return T
    polished = _polish(q, box, T, c)
    if polished is None:
        return T
    if c.planar_motion:
        polished = _planar(polished, q, T_ego)
    if _lifts_centroid(polished, q.mean(axis=0), T_ego, c):
        return T
    f2, r2 = _score(q, polished, surface, c)
    return polished if _keeps_polish((f2, r2), (fitness, rmse), len(q), c) else T


def _keeps_polish(polished: tuple[float, float], icp: tuple[float, float], n: int, c: ObjectRefinementConfig) -> bool:
    """Whether a polish with (fitness, inlier RMSE) ``polished`` replaces the ICP result
    with ``icp`` (both measured on ``n`` points): its RMSE is no larger and its fitness
    lower by at most :func:`_fitness_margin`."""
    return polished[0] >= icp[0] - _fitness_margin(icp[0], n, c) and polished[1] <= icp[1]


def _planar(T: np.ndarray, p: np.ndarray, T_ego: np.ndarray) -> np.ndarray:
    """The motion ``D T_ego`` nearest to ``T`` on the points ``p`` (frame k-1; least squares
    of the landings, m) whose ``D`` (frame k) turns only about the z axis: a translation
    and a yaw from the ego landings ``T_ego p`` to the landings ``T p``."""
    ego, landing = transform_points(T_ego, p), transform_points(T, p)
    ego_mean, land_mean = ego.mean(axis=0), landing.mean(axis=0)
    a, b = ego[:, :2] - ego_mean[:2], landing[:, :2] - land_mean[:2]  # centred BEV positions
    yaw = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    D = np.eye(4)
    D[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    D[:3, 3] = land_mean - D[:3, :3] @ ego_mean
    return D @ T_ego


def _moving(landing: np.ndarray, ego: np.ndarray, interval: float, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: the landings (M,3, frame k) depart from the ego landings ``ego`` by more
    than ``dynamic_speed_mps`` over ``interval`` s (:func:`_departures`)."""
    return _departures(landing, ego, c) > c.dynamic_speed_mps * interval


def _departures(landing: np.ndarray, ego: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) distance (m) of the landings (M,3, frame k) from the ego landings ``ego``:
    horizontally with ``horizontal_departure``, else in 3D."""
    departure = landing - ego
    if c.horizontal_departure:
        departure = departure[:, :2]
    return np.linalg.norm(departure, axis=1)


def _lifts_centroid(T: np.ndarray, centroid: np.ndarray, T_ego: np.ndarray, c: ObjectRefinementConfig) -> bool:
    """Whether the motion ``T`` moves an object's ``centroid`` (frame k-1) up or down from its
    ``T_ego`` landing (:func:`_lifted`)."""
    return bool(_lifted(T[:3, :3] @ centroid + T[:3, 3] - (T_ego[:3, :3] @ centroid + T_ego[:3, 3]), c))


def _lifted(departure: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray:
    """Whether each departure (..., 3) (m, sensor frame k) from an ego landing goes up or down
    by more than ``vertical_margin_m`` + ``vertical_grade`` x its horizontal length: objects
    move on the ground."""
    departure = np.asarray(departure)
    return np.abs(departure[..., 2]) > c.vertical_margin_m + c.vertical_grade * np.hypot(departure[..., 0], departure[..., 1])


def _plane_distances(x: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) distance (m) of each point ``x`` (frame k) to the tangent plane of its nearest
    scan-k point when that is within ``score_distance_m``; inf beyond, NaN without a normal."""
    return _surface_distances(x, surface, c)[1]


def _surface_distances(x: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> tuple:
    """((M,) distance (m) of each point ``x`` (frame k) to its nearest scan-k point, inf
    beyond ``score_distance_m``; (M,) :func:`_plane_distances`), from one nearest-point search."""
    dist, ok, j, normals = _nearest_normals(x, surface, c)
    plane = np.full(len(x), np.inf)
    if ok.size:
        plane[ok] = np.abs(np.einsum("ij,ij->i", x[ok] - surface.points[j], normals))
    return dist, plane


class _EgoLandings:
    """:func:`_surface_distances` of the ego landings of points of ``source`` (frame k-1,
    under ``T_ego``), each point asked of scan k's ``surface`` once per round: the static
    scores, the leftover test, the landing choice and the instance split all ask them."""

    def __init__(self, source: np.ndarray, T_ego: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig):
        self.source, self.T_ego, self.surface, self.c = source, T_ego, surface, c
        self.dist = np.empty(len(source))
        self.plane = np.empty(len(source))
        self.known = np.zeros(len(source), dtype=bool)

    def __call__(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point distance, plane distance) (m) of the ego landings of ``source[idx]``."""
        todo = np.unique(idx[~self.known[idx]])
        if todo.size:
            x = transform_points(self.T_ego, self.source[todo])
            self.dist[todo], self.plane[todo] = _surface_distances(x, self.surface, self.c)
            self.known[todo] = True
        return self.dist[idx], self.plane[idx]


def _nearest_normals(x: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> tuple:
    """((M,) distance (m) of each point ``x`` (frame k) to its nearest scan-k point, inf
    beyond ``score_distance_m``; the indices of the points with one; that point's index in
    ``surface``, its tangent-plane normal (NaN: none)) for those."""
    dist, j = surface.nearest(x, c.score_distance_m)
    ok = np.flatnonzero(np.isfinite(dist))
    if ok.size == 0:
        return dist, ok, ok, np.zeros((0, 3))
    return dist, ok, j[ok], surface.normals(j[ok], c.normal_radius_m)


def _fit(plane: np.ndarray, c: ObjectRefinementConfig) -> tuple[float, float]:
    """(fitness, RMSE) of points with these plane distances: a point is an inlier within
    ``score_plane_m`` of the plane (NaN and inf compare False); RMSE of the inliers' (m)."""
    inlier = plane < c.score_plane_m
    if not inlier.any():
        return 0.0, float("inf")
    return float(inlier.sum()) / len(plane), float(np.sqrt(np.mean(plane[inlier] ** 2)))


def _score(src: np.ndarray, T: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig):
    """(fitness, RMSE) of ``T src`` against the target surface (:func:`_fit` of
    :func:`_plane_distances`). Plane, not point, distances: a static surface seen by other
    rings in scan k is still a surface."""
    return _fit(_plane_distances(transform_points(T, src), surface, c), c)


def _icp_subset(n: int, c: ObjectRefinementConfig) -> np.ndarray:
    """Indices of the at most ``max_icp_points`` of an object's ``n`` points that its ICP uses
    (evenly strided, first and last included)."""
    return np.arange(n) if n <= c.max_icp_points else np.linspace(0, n - 1, c.max_icp_points).round().astype(np.int64)


def _ego_explains(static_score: tuple[float, float], fitness: float, rmse: float, n: int,
                  c: ObjectRefinementConfig, rmse_ratio: float | None = None) -> bool:
    """Whether the ego motion (``static_score``: its fitness and inlier RMSE) explains an
    object as well as the object's own ICP (``fitness``, ``rmse`` (m), measured on ``n``
    points): its fitness is within ``static_preference`` of the ICP's (or within
    ``static_preference_sigmas`` standard errors of a share of n points, if more: one point
    of 15 is 0.067 of fitness) and its inlier RMSE at most ``static_rmse_ratio`` times the
    ICP's + 5 mm (``rmse_ratio`` instead, when given: the parts test's
    ``part_rmse_ratio``), or at most ``static_rmse_floor_m`` (what a static surface scatters:
    a six-degree-of-freedom ICP lowers the RMSE of a small piece of any body a little)."""
    static_fitness, static_rmse = static_score
    if static_fitness < fitness - _fitness_margin(fitness, n, c):
        return False
    ratio = c.static_rmse_ratio if rmse_ratio is None else rmse_ratio
    return static_rmse <= ratio * rmse + 0.005 or static_rmse <= c.static_rmse_floor_m


def _fitness_margin(fitness: float, n: int, c: ObjectRefinementConfig) -> float:
    """How much more fitness than ``fitness`` (measured on ``n`` points) is evidence:
    ``static_preference``, or ``static_preference_sigmas`` standard errors of a share of
    ``n`` points if more."""
    return max(c.static_preference, c.static_preference_sigmas * float(np.sqrt(fitness * (1.0 - fitness) / max(n, 1))))


def _hidden(ego: np.ndarray, range_image, guesses, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: which of an object's ego landings ``ego`` (frame k) scan k hides behind
    something static: a return clearly in front of them whose position is not within
    ``hidden_occluder_m`` of a candidate's input-flow landing (``guesses``, a KD-tree, or
    None: any return counts). A walker hidden by another walker, or a car hidden by its
    own new surface, is hidden by a possible mover."""
    front, where = range_image.in_front(ego)
    if guesses is not None and front.any():
        near = np.isfinite(guesses.query(where[front], distance_upper_bound=c.hidden_occluder_m)[0])
        front[np.flatnonzero(front)[near]] = False
    return front


def _hidden_points(ego: np.ndarray, guess: np.ndarray, range_image, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: points whose ego landing ``ego`` (frame k) scan k hides behind a return
    farther than ``hidden_occluder_m`` from the point's own input-flow landing ``guess``."""
    front, where = range_image.in_front(ego)
    return front & (np.linalg.norm(where - guess, axis=1) > c.hidden_occluder_m)


def _hidden_rest(p: np.ndarray, ego: np.ndarray, flow: np.ndarray, on_surface: np.ndarray, evidence: np.ndarray,
                 range_image, c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: which of the network's leftover dynamic points ``p`` (frame k-1; ``ego``
    their ego landings, ``on_surface`` whether those are on scan k's surface, ``evidence``
    geometric movers or seen-through) scan k hides (:func:`_hidden_points`) within a BEV
    cluster (``cluster_cell_m``) whose other off-surface landings are mostly hidden too:
    less than ``hidden_rest_free_share`` of it lands in view and off scan k's surface, where
    a mover's visible part would have gone (points of clusters cut by ``max_range_m`` or
    too small for an object, and of objects whose ICP was not accepted)."""
    hidden = ~evidence & _hidden_points(ego, p + flow, range_image, c)
    if not hidden.any():
        return hidden
    labels = bev_clusters(p, c.cluster_cell_m)
    free = np.bincount(labels, weights=~on_surface & ~hidden) / np.bincount(labels)
    return hidden & (free[labels] < c.hidden_rest_free_share)


def _visible(ego: np.ndarray, ego_plane: np.ndarray, guess: np.ndarray, range_image,
             c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: which ego landings ``ego`` (frame k; ``ego_plane`` their
    :func:`_plane_distances`) scan k sees: on its surface, or not :func:`_hidden` behind a
    return away from the object's (or part's) own input-flow landings ``guess`` (M,3)."""
    from scipy.spatial import cKDTree

    own = cKDTree(guess) if c.hidden_occluder_m > 0 else None
    return (ego_plane < c.score_plane_m) | ~_hidden(ego, range_image, own, c)


def _static_where_hidden(ego: np.ndarray, ego_plane: np.ndarray, guess: np.ndarray, range_image, guesses,
                         c: ObjectRefinementConfig) -> bool:
    """Whether scan k's hiding explains why the ego motion does not fit an object (its ego
    landings ``ego``, their :func:`_plane_distances` ``ego_plane`` and its input-flow
    landings ``guess``, (M,3) frame k): at least
    ``hidden_static_share`` of the ego landings are :func:`_hidden` (behind something
    away from every candidate's input-flow landing, ``guesses``), or at least
    ``visible_static_share`` are visible (on scan k's surface, or not hidden behind
    something away from the object's own input-flow landing) and those pass the static
    acceptance on their own
    (fitness ``static_fitness_accept``, inlier RMSE ``static_accept_rmse_m``). Scan k
    lacks returns where the rest landed, which is no evidence of motion."""
    if not len(ego):
        return False
    if c.hidden_static_share <= 1 and _hidden(ego, range_image, guesses, c).mean() >= c.hidden_static_share:
        return True
    if c.visible_static_share > 1:
        return False
    visible = _visible(ego, ego_plane, guess, range_image, c)
    if visible.mean() < c.visible_static_share:
        return False
    fitness, rmse = _fit(ego_plane[visible], c)
    return fitness >= c.static_fitness_accept and rmse <= c.static_accept_rmse_m


def _principal_axis(points: np.ndarray) -> np.ndarray:
    """Unit principal axis (x, y, 0) of the BEV spread of (N,3) points."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    v = np.linalg.eigh(xy.T @ xy)[1][:, 1]
    return np.array([v[0], v[1], 0.0])



def scan_interval(dt: float | None) -> float:
    """The scan interval (s) the objects' speeds use: ``dt``, or 0.1 s (a 10 Hz sensor) when
    it is missing or not positive."""
    return dt if dt and dt > 0 else 0.1


def refine_objects(
    source: np.ndarray,
    flow: np.ndarray,
    dynamic: np.ndarray,
    target: np.ndarray,
    T_ego: np.ndarray,
    dt: float,
    config: ObjectRefinementConfig | None = None,
    target_points: np.ndarray | None = None,
    movers: np.ndarray | None = None,
    seen_through: np.ndarray | None = None,
    surface: ScanSurface | None = None,
    above_ground: np.ndarray | None = None,
    range_image=None,
    tracked: np.ndarray | None = None,
    older: OlderView | None = None,
) -> ObjectRefinement:
    """Refine the flow of the candidate moving points of ``source`` (scan k-1) against
    ``target`` (scan k) given the ego motion ``T_ego`` = ``T_{k,k-1}`` (module doc), in at
    most ``iterations`` rounds (SSF-PAN's flow <-> segmentation loop): round i+1 takes
    round i's flow and dynamic labels as its input, and keeps the geometric movers round i
    left dynamic. The result is the last round's, with ``stats["iterations"]`` (rounds
    run) and ``stats["round_changes"]`` (labels changed by each round after the first).

    ``flow`` (N,3) is the network's flow, ``dynamic`` (N,) its labels, ``dt`` the scan
    interval (s). In the result, static points have the ego-rigid flow of ``T_ego``,
    registered objects their own rigid flow, other dynamic points the network's flow (with
    ``flat_motion``, every dynamic point's flow keeps its ego landing's height). ``target_points``
    (frame k) may be a downsampling of ``target`` (the static refinement's) for the test of
    the dynamic points outside every object (default: ``target``). ``movers`` and
    ``seen_through`` (N,) bool: geometric motion evidence
    (:func:`flowslam.sceneflow.refinement.visibility.geometric_movers`); movers become candidates, and
    objects with seen-through points also start ICP from shifted ego landings
    (``hypotheses_m``), since free space says *that* they moved, not where to.
    ``surface``: a :class:`ScanSurface` of ``target`` to share (it must hold the target
    points within ``max_range_m + margin_m + 5`` m, horizontally); built here when not given.
    ``above_ground`` (N,) bool: points clear of scan k-1's local ground; with it, clusters
    with fewer than ``min_above_ground_points`` such points are road (static, no ICP) and
    moving objects may grow (``grow_max_extent_m``). ``range_image``: a
    :class:`~flowslam.sceneflow.refinement.visibility.RangeImage` of ``target``; with it, an
    object without geometric movers or seen-through points stays static when scan k hides
    where the ego motion puts it (:func:`_static_where_hidden`). ``tracked`` (N,) bool: the
    candidates the mover track carried from the last pair that may form tracked parts
    (``tracked_parts_min_points``; the objects stage passes those the network flags too).
    ``older``: an older scan's free space, for the slide test (``slide_free_share``).
    """
    c = config or ObjectRefinementConfig()
    if target_points is None:
        target_points = target
    if surface is None:
        surface = ScanSurface(target, object_target_range(c))
    movers = np.zeros(len(source), dtype=bool) if movers is None else np.asarray(movers, dtype=bool)
    seen = np.zeros(len(source), dtype=bool) if seen_through is None else np.asarray(seen_through, dtype=bool)
    interval = scan_interval(dt)
    scene = (source, T_ego, interval, target_points, seen, surface, above_ground, range_image, c, tracked, older)
    result = _refine_round(np.array(flow, dtype=np.float64), np.array(dynamic, dtype=bool), movers, *scene)
    changes = []
    while len(changes) + 1 < c.iterations:
        nxt = _refine_round(result.flow.copy(), result.dynamic.copy(), movers & result.dynamic, *scene)
        relabelled = int(np.count_nonzero(nxt.dynamic != result.dynamic))
        either = int(np.count_nonzero(nxt.dynamic | result.dynamic))
        both = nxt.dynamic & result.dynamic  # a relabelled point counts in ``relabelled`` only
        moved = float(np.linalg.norm(nxt.flow[both] - result.flow[both], axis=1).mean()) if both.any() else 0.0
        changes.append(relabelled)
        result = nxt
        if relabelled <= c.converged_share * either and moved <= c.converged_flow_m:
            break
    if c.flat_motion:
        _level(source, result.flow, np.flatnonzero(result.dynamic), T_ego)
    result.stats.update(iterations=len(changes) + 1, round_changes=changes)
    return result


def _level(source: np.ndarray, flow: np.ndarray, idx: np.ndarray, T_ego: np.ndarray) -> None:
    """``flat_motion``: the ``flow`` (updated in place) of the points ``idx`` of ``source``
    (frame k-1) with the height of their ego landings (``T_ego`` = ``T_{k,k-1}``; frame k,
    z up): each departs from its ego landing horizontally only."""
    if idx.size:
        flow[idx, 2] = rigid_flow(T_ego, source[idx])[:, 2]


def hold_tracks(source: np.ndarray, result: ObjectRefinement, tracked: np.ndarray, tracked_flow: np.ndarray,
                T_ego: np.ndarray, dt: float, surface: ScanSurface, older, c: ObjectRefinementConfig) -> int:
    """Tracked movers that :func:`refine_objects` left static keep moving with their
    predicted flow (``hold_tracks`` in the config: the conditions). ``source``: scan k-1
    (frame k-1); ``result``: its refinement, updated in place (each held component becomes
    an accepted object with ``held: True``); ``tracked`` (N,) bool and ``tracked_flow``
    (N,3): :meth:`~flowslam.sceneflow.refinement.tracking.MoverPrior.predict`; ``T_ego`` =
    ``T_{k,k-1}``; ``dt``: the scan interval (s, :func:`scan_interval`); ``surface``: scan
    k; ``older``: (range image of the scan ``baseline_scans`` before scan k-1,
    ``T_old_{k-1}``) or None (no older scan: no track is held). Returns the number of
    points held."""
    if not c.hold_tracks or older is None:
        return 0
    stale = np.flatnonzero(np.asarray(tracked, bool) & ~result.dynamic)
    if stale.size < c.min_points:
        return 0
    image, T_old = older
    interval = scan_interval(dt)
    margin, relative = baseline_window_margins(c.motion_evidence)
    held = 0
    for idx in _bev_groups(source, stale, c.instance_cell_m, c.min_points):
        p = source[idx]
        ego, landing = transform_points(T_ego, p), p + tracked_flow[idx]
        speed = float(np.linalg.norm(landing - ego, axis=1).mean()) / interval
        if speed <= c.dynamic_speed_mps:
            continue
        fitness = _fit(_plane_distances(landing, surface, c), c)[0]
        if fitness < c.min_fitness or fitness < _fit(_plane_distances(ego, surface, c), c)[0] - c.static_preference:
            continue
        free = image.sees_beyond(transform_points(T_old, p), margin_m=margin, relative_margin=relative)
        if free.mean() < c.hold_free_share:
            continue
        result.flow[idx], result.dynamic[idx], result.instance[idx] = landing - p, True, len(result.objects)
        if c.flat_motion:
            _level(source, result.flow, idx, T_ego)
        result.objects.append({"points": int(len(idx)), "accepted": True, "held": True, "fitness": fitness,
                               "speed_mps": speed})
        held += len(idx)
    return held


def release_tracks(source: np.ndarray, result: ObjectRefinement, tracked: np.ndarray | None, shown: np.ndarray,
                   T_ego: np.ndarray, older, span_s: float, c: ObjectRefinementConfig) -> int:
    """Moving instances the mover track carried that an older scan saw in place become
    static (``release_seen_share`` in the config: the conditions; the reverse of
    :func:`hold_tracks`). ``source``: scan k-1 (frame k-1); ``result``: its refinement, updated
    in place (a released instance's points get the ego-rigid flow of ``T_ego`` =
    ``T_{k,k-1}``, no instance, and its record ``accepted: False``, ``released: True`` and
    ``seen_in_place``, the share of its points with a known window that the older scan saw
    in place); ``tracked`` (N,) bool: the points the track carried
    (:meth:`~flowslam.sceneflow.refinement.tracking.MoverPrior.predict`; None: every instance
    is asked, ``release_any_prior``); ``shown`` (N,) bool: the points whose instance showed
    motion of its own this pair
    (:func:`~flowslam.sceneflow.refinement.tracking.object_evidence`); ``older``: (range image
    of the scan ``motion_evidence.baseline_scans`` before scan k-1, ``T_old_{k-1}``) or None
    (nothing is released); ``span_s``: the time (s) from that scan to scan k-1. Returns the
    number of points released."""
    if c.release_seen_share <= 0 or older is None:
        return 0
    image, T_old = older
    shown = np.asarray(shown, dtype=bool)
    carried = result.dynamic & ~shown & (result.instance >= 0)
    if tracked is not None:
        carried &= np.asarray(tracked, dtype=bool)
    released = 0
    for j in np.unique(result.instance[carried]):
        record = result.objects[j]
        if record.get("speed_mps", 0.0) * span_s < c.release_min_shift_m:
            continue
        idx = np.flatnonzero(result.instance == j)
        known, there = image.seen_at(transform_points(T_old, source[idx]), c.release_margin_m)
        if not known.any() or known.mean() < c.release_min_known or there.sum() < c.release_seen_share * known.sum():
            continue
        released += release_instance(source, result, j, idx, T_ego,
                                     seen_in_place=float(there.sum()) / float(known.sum()))
    return released


def release_instance(source: np.ndarray, result: ObjectRefinement, j: int, idx: np.ndarray, T_ego: np.ndarray,
                     **why) -> int:
    """Make moving instance ``j`` of ``result`` static after all: its points ``idx`` (indices
    into ``source``, scan k-1, frame k-1: those with ``result.instance == j``) get the ego-rigid
    flow of ``T_ego`` = ``T_{k,k-1}``, no instance, and its record ``accepted: False``,
    ``released: True`` and the ``why`` entries. Returns the number of points released."""
    result.flow[idx], result.dynamic[idx], result.instance[idx] = rigid_flow(T_ego, source[idx]), False, -1
    result.objects[j].update(accepted=False, released=True, **why)
    return len(idx)


def _refine_round(flow: np.ndarray, dynamic: np.ndarray, movers: np.ndarray, source: np.ndarray, T_ego: np.ndarray,
                  interval: float, target_points: np.ndarray, seen: np.ndarray, surface: ScanSurface,
                  above_ground: np.ndarray | None, range_image, c: ObjectRefinementConfig,
                  tracked: np.ndarray | None = None, older: OlderView | None = None) -> ObjectRefinement:
    """One round of :func:`refine_objects` (its arguments, prepared; ``flow`` and ``dynamic``
    are updated in place and returned in the result)."""
    range2 = np.einsum("ij,ij->i", source[:, :2], source[:, :2])
    clear = range2 >= c.min_range_m ** 2  # beyond the ego vehicle's body
    near = clear & (range2 < c.max_range_m ** 2)
    cand = np.flatnonzero((dynamic & near) | (movers & clear))
    objects = []
    settled = np.zeros(len(source), dtype=bool)
    instance = np.full(len(source), -1, dtype=np.int64)
    far = None if c.min_points_far is None else (c.min_points_far, c.far_from_m)
    clusters = _bev_groups(source, cand, c.cluster_cell_m, c.min_points, far)
    if far is not None:  # a far cluster under min_points: only on geometric evidence
        clusters = [idx for idx in clusters
                    if len(idx) >= c.min_points or np.count_nonzero(movers[idx]) >= c.min_points_far]
    guesses = None  # where the candidates land by their input flow: scan k's possible movers
    if range_image is not None and c.hidden_static_share <= 1 and c.hidden_occluder_m > 0 and cand.size:
        from scipy.spatial import cKDTree

        guesses = cKDTree(source[cand] + flow[cand])
    road = 0
    if above_ground is not None and c.min_above_ground_points > 0:  # clusters flat on the ground: road
        on_road = [int(np.count_nonzero(above_ground[idx])) < c.min_above_ground_points for idx in clusters]
        for idx in (idx for idx, flat in zip(clusters, on_road) if flat):
            flow[idx], dynamic[idx], settled[idx] = rigid_flow(T_ego, source[idx]), False, True
        clusters, road = [idx for idx, flat in zip(clusters, on_road) if not flat], int(sum(on_road))
    grown = []  # (object, its motion, its dynamic points) to grow
    motions = {}  # object -> its own motion
    motion_of = np.full(len(source), -1, dtype=np.int64)  # index of the object motion a point took
    ego_landings = _EgoLandings(source, T_ego, surface, c)  # shared by this round's tests of ego landings
    scene = (source, flow, movers, seen, T_ego, interval, surface, c, range_image, guesses, above_ground)
    for idx, record in _registered(clusters, *scene, ego_landings=ego_landings, tracked=tracked, older=older):
        own = instance[idx] = len(objects)
        motion = record.pop("motion", None)
        if motion is not None:
            motions[own] = motion
        objects.append(record)
        if "result" in record:
            landing, moving, motion_of[idx] = record.pop("result")
            flow[idx], dynamic[idx], settled[idx] = landing - source[idx], moving, True
            if motion is not None and moving.any():
                grown.append((own, motion, idx[moving]))
    solid = None if above_ground is None else np.flatnonzero(np.asarray(above_ground, bool) & near)

    def join(joined, key: str) -> None:  # (object, points, landings, moving) that join moving objects
        for i, extra, landing, moving in joined:
            flow[extra], dynamic[extra], settled[extra], instance[extra] = landing - source[extra], moving, True, i
            motion_of[extra] = 0
            objects[i][key] = int(len(extra))

    if grown and solid is not None and c.grow_max_extent_m > 0:
        evidence = seen  # the growth's free-space evidence; far off, also the other tests' flags
        if c.grow_movers_from_m is not None:
            evidence = seen | (movers & (range2 >= c.grow_movers_from_m ** 2))
        join(_grow(source, solid, grown, settled, evidence, T_ego, surface, interval, c), "grown_points")
    if grown and solid is not None and c.grow_footprint_cell_m > 0:
        join(_footprint(source, solid, grown, settled, T_ego, surface, interval, c), "footprint_points")
    if motions and solid is not None and c.embedded_share <= 1:
        solid_points = source[solid]
        for own, motion in motions.items():
            mine = np.flatnonzero((instance == own) & dynamic & settled)
            if mine.size and _embedded(source, solid, solid_points, mine, motion, T_ego, surface, c):
                flow[mine], dynamic[mine] = rigid_flow(T_ego, source[mine]), False
                objects[own]["embedded"] = True
    still = _split_instances(source, flow, dynamic & settled, instance, motion_of, objects, T_ego, interval, surface, c,
                             range_image if c.split_visible else None, seen,
                             above_ground if c.split_above_ground else None, ego_landings=ego_landings)
    flow[still], dynamic[still] = rigid_flow(T_ego, source[still]), False
    # the rest of the network's dynamic points: static if the ego motion lands them on a surface
    # of scan k; those outside the candidates' range (in no object) ask every point of scan k,
    # since the refinement's target points lack those near the network's dynamic
    # landings, which is where a false flag's ego landings lie
    rest = np.flatnonzero(dynamic & ~settled)
    on_surface = np.zeros(0, dtype=bool)
    if rest.size:
        rigid = transform_points(T_ego, source[rest])
        on_surface = within_any(rigid, target_points, c.off_surface_m)
        outside = np.flatnonzero(~near[rest] & ~on_surface)
        on_surface[outside] = surface.near_any(rigid[outside], c.off_surface_m)
        if range_image is not None and c.hidden_rest_free_share > 0:
            on_surface |= _hidden_rest(source[rest], rigid, flow[rest], on_surface, movers[rest] | seen[rest],
                                       range_image, c)
        dynamic[rest[on_surface]] = False
    slow_rest = 0
    if c.rest_min_speed_mps > 0:
        slow = _slow_rest(source, flow, np.flatnonzero(dynamic & ~settled & clear), instance, len(objects), T_ego,
                          interval, movers | seen, c)
        dynamic[slow], slow_rest = False, int(slow.size)
    static = ~dynamic & ~settled
    flow[static] = rigid_flow(T_ego, np.compress(static, source, axis=0))  # boolean indexing's rows, ~4x faster
    unregistered = 0
    if c.unregistered_instances:
        unregistered = _number_unregistered(source, flow, dynamic & clear, instance, objects, T_ego, interval,
                                            above_ground if c.split_above_ground else None, c)
    stats = {
        "object_candidates": int(cand.size),
        "objects": len(objects),
        "objects_accepted": sum(o["accepted"] for o in objects),
        "objects_dynamic": sum(1 for o in objects if o.get("speed_mps", 0.0) > c.dynamic_speed_mps),
        "relabelled_static": int(on_surface.sum()),
        "rest_static_slow": slow_rest,
        "road_clusters": road,
        "unregistered_instances": unregistered,
    }
    return ObjectRefinement(flow, dynamic, instance, objects, stats)


def object_target_range(c: ObjectRefinementConfig) -> float:
    """Horizontal range (m) of the target points the objects are registered to."""
    return c.max_range_m + c.margin_m + 5.0


def _grow(source: np.ndarray, solid: np.ndarray, grown: list, settled: np.ndarray, seen: np.ndarray,
          T_ego: np.ndarray, surface: ScanSurface, interval: float, c: ObjectRefinementConfig):
    """For each moving object ``(index, motion, its dynamic points)``: the unsettled points of
    the small BEV components of ``solid`` (above-ground point indices) it lies in, when its
    motion explains at least ``min_fitness`` of such a component, the ego motion explains
    less of it by ``static_preference`` (else it is static structure beside the mover: a
    wall a pedestrian walks along) and it holds ``grow_min_seen_through`` seen-through
    points (``seen``: scan k sees through where it was; an object of scan k-1 hidden in
    scan k also fits a shifted surface, but nothing is seen through it); yields ``(index, points,
    their landings (frame k; the ego landing where not moving), moving)`` for the points
    its motion explains."""
    # only components of at most grow_max_extent_m can join, so only points that close to a
    # mover's points (in x and y) can belong to one: the others are not clustered at all
    reach = c.grow_max_extent_m + c.cluster_cell_m
    xy = source[solid, :2]
    near = np.zeros(len(solid), dtype=bool)
    for _, _, core in grown:
        near |= in_bounds(xy, source[core, :2].min(axis=0) - reach, source[core, :2].max(axis=0) + reach)
    solid = solid[near]  # still sorted
    if solid.size == 0:
        return
    labels = bev_clusters(source[solid], c.cluster_cell_m)
    small = bev_extent(source[solid, :2], labels, int(labels.max()) + 1) <= c.grow_max_extent_m
    label_of = np.full(len(source), -1)
    label_of[solid] = labels
    taken = settled.copy()
    for i, motion, core in grown:
        comps = np.unique(label_of[core])
        comps = comps[(comps >= 0)]
        groups = [(solid[labels == comp], motion) for comp in comps[small[comps]]]
        if c.grow_wide_margin <= 1:
            groups += [(part, None) for comp in comps[~small[comps]]
                       for part in _parts_holding(source, solid[labels == comp], core, c)]
        for members, own in groups:
            if seen[members].sum() < c.grow_min_seen_through:
                continue
            margin = None  # _joins' own: static_preference
            if own is None:  # a part of a wide component: its motion refitted on it, from the object's
                if _ego_lands_near(source[members], T_ego, surface, c):
                    continue
                own, margin = _refit(source[members], motion, surface, c), c.grow_wide_margin
            joined = _joins(source, members, taken, own, T_ego, surface, interval, c, margin)
            if joined is not None:
                taken[joined[0]] = True
                yield (i, *joined)


def _parts_holding(source: np.ndarray, members: np.ndarray, core: np.ndarray, c: ObjectRefinementConfig) -> list:
    """The ``instance_cell_m`` BEV components of ``members`` (indices into ``source``) that
    hold a point of ``core`` and span at most ``grow_max_extent_m``: a vehicle's own body
    inside a component that the coarser cell joined to the trees or walls beside it."""
    labels = bev_clusters(source[members], c.instance_cell_m)
    small = bev_extent(source[members, :2], labels, int(labels.max()) + 1) <= c.grow_max_extent_m
    held = np.unique(labels[np.isin(members, core)])
    return [members[labels == part] for part in held[small[held]]]


def _ego_lands_near(p: np.ndarray, T_ego: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> bool:
    """Whether at least ``grow_wide_ego_near_share`` of the points ``p`` (frame k-1) land within
    ``grow_wide_ego_near_m`` of a scan-k point under the ego motion ``T_ego`` (False when that
    is 0)."""
    if c.grow_wide_ego_near_m <= 0:
        return False
    dist, _ = surface.nearest(transform_points(T_ego, p), c.grow_wide_ego_near_m)
    return np.count_nonzero(np.isfinite(dist)) >= c.grow_wide_ego_near_share * len(p)


def _refit(q: np.ndarray, motion: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> np.ndarray:
    """``motion`` refined by :func:`_register` of the points ``q`` (frame k-1) onto scan k's
    points around their landing (``margin_m``); ``motion`` itself where that gives up."""
    landing = transform_points(motion, q)
    box = surface.in_box(landing.min(axis=0) - c.margin_m, landing.max(axis=0) + c.margin_m)
    if len(box) < c.min_points:
        return motion
    refitted = _register(q, IcpTarget(box), motion, c)
    return motion if refitted is None else refitted


def _joins(source: np.ndarray, members: np.ndarray, taken: np.ndarray, motion: np.ndarray, T_ego: np.ndarray,
           surface: ScanSurface, interval: float, c: ObjectRefinementConfig, margin: float | None = None):
    """The points of ``members`` (indices into ``source``) that join a moving object of
    ``motion``: when its motion puts at least ``min_fitness`` of them on scan k's surface
    and the ego motion puts fewer there by ``static_preference`` (or ``margin``; else they
    are static structure beside the mover: a wall a pedestrian walks along), those its motion explains
    (with ``grow_unexplained``, also those neither motion puts on the surface: hidden in
    scan k) and not yet ``taken``, as (points, their landings (frame k; the ego landing where
    not moving), moving); else None."""
    landing = transform_points(motion, source[members])
    explained = _plane_distances(landing, surface, c) < c.score_plane_m
    if explained.mean() < c.min_fitness:
        return None
    ego_explained = _plane_distances(transform_points(T_ego, source[members]), surface, c) < c.score_plane_m
    if ego_explained.mean() >= explained.mean() - (c.static_preference if margin is None else margin):
        return None
    extra = (explained | (c.grow_unexplained & ~ego_explained)) & ~taken[members]
    if not extra.any():
        return None
    pts = members[extra]
    ego = transform_points(T_ego, source[pts])
    moving = _moving(landing[extra], ego, interval, c)
    return pts, np.where(moving[:, None], landing[extra], ego), moving  # static: the ego landing


FOOTPRINT_MAX_EXTENT_M = 1.5
"""Objects wider than this (BEV diagonal of their moving points, m) do not take their
footprint (:func:`_footprint`): walkers and cyclists do; a vehicle's unflagged parts join by
the growth's free-space test (real KITTI 0-15: a 5 m stretch of a static double wall that
one ICP slid took 700 more points by its footprint)."""


def _footprint(source: np.ndarray, solid: np.ndarray, grown: list, settled: np.ndarray, T_ego: np.ndarray,
               surface: ScanSurface, interval: float, c: ObjectRefinementConfig):
    """For each moving object ``(index, motion, its dynamic points)``: the unsettled points of
    ``solid`` (above-ground point indices) in the object's own BEV cells (``grow_footprint_cell_m``)
    that :func:`_joins` lets join it, as ``(index, points, landings, moving)``, for objects
    whose moving points span at most ``FOOTPRINT_MAX_EXTENT_M`` (BEV diagonal). A walker's
    legs under its flagged torso: the same footprint needs no free space of its own."""
    taken, cell = settled.copy(), c.grow_footprint_cell_m
    solid_xy = source[solid, :2]
    for i, motion, core in grown:
        if np.hypot(*np.ptp(source[core, :2], axis=0)) > FOOTPRINT_MAX_EXTENT_M:
            continue
        cells = np.unique(np.floor(source[core, :2] / cell).astype(np.int64), axis=0)
        lo, hi = cells.min(axis=0) * cell, (cells.max(axis=0) + 1) * cell
        near = solid[in_bounds(solid_xy, lo, hi)]
        near = near[~taken[near]]
        if near.size == 0:
            continue
        own = np.floor(source[near, :2] / cell).astype(np.int64)
        members = near[(own[:, None, :] == cells[None, :, :]).all(axis=2).any(axis=1)]
        if members.size == 0:
            continue
        joined = _joins(source, members, taken, motion, T_ego, surface, interval, c)
        if joined is not None:
            taken[joined[0]] = True
            yield (i, *joined)


EMBED_RADIUS_M = 0.15
"""A moving point with another point clear of the ground this close (m) lies inside a body
(:func:`_embedded`)."""

EMBED_BODY_M = 0.5
"""The body around an embedded object: the other points clear of the ground within this
distance (m) of its moving points."""


def _embedded(source: np.ndarray, solid: np.ndarray, solid_points: np.ndarray, mine: np.ndarray, motion: np.ndarray,
              T_ego: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> bool:
    """Whether an object's moving points ``mine`` (indices into ``source``, frame k-1) are a
    part of a static body that its ``motion`` slid: at least ``embedded_share`` of them have
    another point of ``solid`` (indices of the points clear of the ground; ``solid_points``
    = ``source[solid]``) within ``EMBED_RADIUS_M``, and the ego motion puts that body (the
    other ``solid`` points within ``EMBED_BODY_M`` of them; at most ``max_icp_points`` of
    them, evenly strided) on scan k's ``surface`` better than ``motion`` does, by
    ``static_preference`` (:func:`_score` fitness). A walker beside a parked car touches it
    only at its edge; a moving vehicle's unflagged points move with it."""
    from scipy.spatial import cKDTree

    p = source[mine]
    near = solid[in_bounds(solid_points, p.min(axis=0) - EMBED_BODY_M, p.max(axis=0) + EMBED_BODY_M)]
    others = source[near[~np.isin(near, mine)]]
    if len(others) == 0:
        return False
    inside = np.isfinite(cKDTree(others).query(p, distance_upper_bound=EMBED_RADIUS_M)[0]).mean()
    if inside < c.embedded_share:
        return False
    body = others[np.isfinite(cKDTree(p).query(others, distance_upper_bound=EMBED_BODY_M)[0])]
    body = body[_icp_subset(len(body), c)]
    return _score(body, T_ego, surface, c)[0] >= _score(body, motion, surface, c)[0] + c.static_preference


def _registered(clusters: list[np.ndarray], source: np.ndarray, flow: np.ndarray, movers: np.ndarray,
                seen: np.ndarray, T_ego: np.ndarray, interval: float, surface: ScanSurface,
                c: ObjectRefinementConfig, range_image=None, guesses=None, solid: np.ndarray | None = None, *,
                ego_landings: _EgoLandings, tracked: np.ndarray | None = None, older: OlderView | None = None):
    """Yields each cluster (index array into ``source``) with its :func:`_refine_object`
    record (``solid``: (N,) points clear of the ground, or None; ``ego_landings``: the
    round's). A cluster wider than
    ``split_extent_m`` is also registered as its :func:`_components`, and those replace it
    when their registrations explain at least ``split_gain`` of its points more than its
    own (:func:`_explained`): in a crowd or a
    queue one cluster holds several movers, and one rigid motion cannot register them
    all; but a car whose sparse candidate points fall into several components is better
    registered whole (its pieces slide along their own faces, and explain about as much).
    With ``tracked`` and ``tracked_parts_min_points``, a cluster that ends without a moving
    point yields its moving :func:`_tracked_parts` first and then itself without them.
    ``older``: passed to :func:`_refine_object` (the slide test)."""
    def refine(group):
        if group:
            ego_landings(np.concatenate(group))  # the group's ego landings in one query
        for idx in group:
            yield idx, _refine_object(source[idx], flow[idx], movers[idx], seen[idx], T_ego, interval, surface,
                                      ego_landings(idx), c, range_image, guesses, None if solid is None else solid[idx],
                                      ring_slice=lambda idx=idx: _ring_slice(source, idx, solid, c), older=older)

    for idx, record in refine(clusters):
        parts = _components(source, idx, c)
        if len(parts) > 1:
            split = list(refine(parts))
            gained = sum(_explained(r, surface, c) * len(i) for i, r in split) - _explained(record, surface, c) * len(idx)
            if gained >= c.split_gain * len(idx):
                yield from split
                continue
        moved = _tracked_parts(source, idx, record, tracked, c, refine) if tracked is not None else []
        yield from moved
        yield (idx, record) if not moved else _without(idx, record, np.concatenate([i for i, _ in moved]))


def _moves(record: dict) -> bool:
    """Whether an object's record moves any of its points."""
    return "result" in record and bool(record["result"][1].any())


def _tracked_parts(source: np.ndarray, idx: np.ndarray, record: dict, tracked: np.ndarray,
                   c: ObjectRefinementConfig, refine) -> list[tuple[np.ndarray, dict]]:
    """The (points, record) of the ``instance_cell_m`` components of a still cluster's
    (``idx``, ``record``: none of its points moves) ``tracked`` points, of at least
    ``tracked_parts_min_points`` each, that move when registered on their own (``refine``);
    [] when the option is off, the cluster moves, or its tracked points are more than
    ``tracked_parts_max_share`` of it."""
    if c.tracked_parts_min_points <= 0 or _moves(record):
        return []
    mine = idx[tracked[idx]]
    if mine.size < c.tracked_parts_min_points or mine.size > c.tracked_parts_max_share * idx.size:
        return []
    parts = _bev_groups(source, mine, c.instance_cell_m, c.tracked_parts_min_points)
    return [(i, r) for i, r in refine(parts) if _moves(r)]


def _without(idx: np.ndarray, record: dict, taken: np.ndarray) -> tuple[np.ndarray, dict]:
    """The cluster ``idx`` and its ``record`` without the points ``taken`` (indices into the
    scan): its count and its per-point result cut to the points left."""
    keep = ~np.isin(idx, taken)
    record = dict(record, points=int(keep.sum()))
    if "result" in record:
        record["result"] = tuple(a[keep] for a in record["result"])
    return idx[keep], record


def _ring_slice(source: np.ndarray, idx: np.ndarray, solid: np.ndarray | None, c: ObjectRefinementConfig) -> bool:
    """Whether the object ``idx`` (indices into ``source``, frame k-1) lies on fewer of the
    sensor's rings than ``min_rings`` (:func:`~flowslam.sceneflow.refinement.clusters.ring_count`;
    never with ``min_rings`` <= 1) -- and, with ``ring_body_m`` > 0, the body around it does
    not: the points of ``solid`` ((N,) bool, clear of the ground; None: all) within
    ``ring_body_m`` of its points, its own included, lie on at least ``min_rings``. A slice
    of a larger body (a canopy's arc, a car's flank) is then too thin for an ICP to tell a
    motion from a slide onto scan k's next ring, while an object that is thin as a whole (a
    car on a 16-beam sensor's two rings) keeps its ICP."""
    if c.min_rings <= 1 or ring_count(source[idx], c.ring_gap_rad) >= c.min_rings:
        return False
    if c.ring_body_m <= 0:
        return True
    p, r = source[idx], c.ring_body_m
    around = np.flatnonzero(in_bounds(source, p.min(axis=0) - r, p.max(axis=0) + r))
    if solid is not None:
        around = around[solid[around]]
    body = around[within_any(source[around], p, r)]
    return ring_count(source[np.union1d(body, idx)], c.ring_gap_rad) >= c.min_rings


def _explained(record: dict, surface: ScanSurface, c: ObjectRefinementConfig) -> float:
    """Share of an object's points whose landing in its ``result`` (each point's own choice
    among the object's motions and the ego motion) lies within ``score_plane_m`` of scan
    k's surface (:func:`_fit`); 0 when not accepted (no result)."""
    if "result" not in record:
        return 0.0
    return _fit(_plane_distances(record["result"][0], surface, c), c)[0]


def _components(source: np.ndarray, idx: np.ndarray, c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The cluster ``idx`` as its ``instance_cell_m`` components of at least ``min_points``
    (smaller ones join the largest) when its BEV diagonal exceeds ``split_extent_m`` (> 0);
    else ``[idx]``."""
    if c.split_extent_m <= 0 or np.hypot(*np.ptp(source[idx, :2], axis=0)) <= c.split_extent_m:
        return [idx]
    labels, big = _joined_components(source[idx], c)
    return [idx[labels == b] for b in np.sort(big)] if len(big) > 1 else [idx]


def _bev_groups(source: np.ndarray, idx: np.ndarray, cell_m: float, min_points: int,
                far: tuple[int, float] | None = None) -> list[np.ndarray]:
    """The indices ``idx`` (into ``source``) grouped into BEV clusters of ``cell_m`` cells, those
    of at least ``min_points`` points (``far`` = (minimum, range in m): that minimum for clusters
    that far off, :func:`~flowslam.sceneflow.refinement.clusters.cluster_minimum`), each as an
    index array in ``idx``'s order, by label: the objects' candidate clusters, the tracked parts
    of a cluster, the stale tracks to hold."""
    labels = bev_clusters(source[idx], cell_m)
    if labels.size == 0:
        return []
    counts = np.bincount(labels)
    if far is not None:
        min_points = cluster_minimum(source[idx, :2], labels, counts, min_points, *far)
    order = np.argsort(labels, kind="stable")  # indices grouped by cluster
    starts = np.concatenate([[0], np.cumsum(counts)])
    return [idx[order[starts[label]:starts[label + 1]]] for label in np.flatnonzero(counts >= min_points)]


def _mover_starts(p: np.ndarray, sub: np.ndarray, seen: np.ndarray, T_ego: np.ndarray,
                  c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The ego motion shifted by each of ``hypotheses_m`` along the movers' principal BEV axis
    (in frame k), for objects with enough geometric movers ``sub`` and seen-through points."""
    if not (c.hypotheses_m and sub.sum() >= c.min_points and seen.sum() >= c.min_seen_through):
        return []
    return _shifted(p[sub], T_ego, c)


def _shifted(points: np.ndarray, T_ego: np.ndarray, c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The ego motion shifted by each of ``hypotheses_m`` along the principal BEV axis of
    ``points`` (frame k-1), turned into frame k."""
    axis = T_ego[:3, :3] @ _principal_axis(points)
    starts = []
    for d in c.hypotheses_m:
        shifted = T_ego.copy()
        shifted[:3, 3] += d * axis
        starts.append(shifted)
    return starts


def _mover_parts(movers: np.ndarray, starts: list[np.ndarray], T_ego: np.ndarray, c: ObjectRefinementConfig):
    """The geometric movers of an object (``movers``, frame k-1) as the parts its mover ICP
    registers, each with its shifted starts: the whole set with ``starts``, or, when they
    fall into several ``mover_part_cell_m`` BEV components of at least ``min_points`` that
    are wider than ``PERSON_MAX_EXTENT_M``, each such component with starts along its own
    axis (two vehicles that move apart in one cluster).""" 
    if c.mover_part_cell_m > 0:
        labels = bev_clusters(movers, c.mover_part_cell_m)
        counts = np.bincount(labels)
        big = np.flatnonzero(counts >= c.min_points)
        big = big[bev_extent(movers[:, :2], labels, len(counts))[big] > PERSON_MAX_EXTENT_M]
        if len(big) > 1:
            parts = [movers[labels == b] for b in big]
            return [(part, _shifted(part, T_ego, c)) for part in parts]
    return [(movers, starts)]


def _displacement_start(p: np.ndarray, flow: np.ndarray, T_ego: np.ndarray) -> np.ndarray:
    """ICP start of points ``p`` (frame k-1) with input ``flow``: the ego rotation and the
    median displacement of their flow after it."""
    R = T_ego[:3, :3]
    T0 = np.eye(4)
    T0[:3, :3] = R
    T0[:3, 3] = np.median(p + flow - p @ R.T, axis=0)
    return T0


def _target_box(surface: ScanSurface, guess: np.ndarray, ego: np.ndarray, reach: float,
                c: ObjectRefinementConfig) -> np.ndarray:
    """The target points in the box around both landings of the object (its start ``guess``
    and ``ego``), grown by ``margin_m`` + ``reach``."""
    lo = np.minimum(guess.min(axis=0), ego.min(axis=0)) - c.margin_m - reach
    hi = np.maximum(guess.max(axis=0), ego.max(axis=0)) + c.margin_m + reach
    return surface.in_box(lo, hi)


def _refine_object(p: np.ndarray, flow: np.ndarray, sub: np.ndarray, seen: np.ndarray, T_ego: np.ndarray,
                   interval: float, surface: ScanSurface, ego_surface: tuple[np.ndarray, np.ndarray],
                   c: ObjectRefinementConfig, range_image=None, guesses=None, solid: np.ndarray | None = None,
                   ring_slice: Callable[[], bool] | None = None, older: OlderView | None = None) -> dict:
    """Register one object (points ``p``, frame k-1; their flow; its geometric movers ``sub``
    and seen-through points; ``ego_surface``: the :func:`_surface_distances` of their
    landings under ``T_ego``, whose :func:`_fit` is its static score) to scan k,
    ``interval`` (s) after; ``ring_slice``: None, or a function that says whether it lies
    on too few rings (:func:`_ring_slice`; asked only of an object that would get an ICP),
    so that it stays static without one; ``older``: the older scan's free space for
    :func:`_slid` (None: no slide test). Returns its record; an accepted one also holds
    ``result``: (landing (M,3) of each point in frame k, moving (M,) bool)."""
    ego = transform_points(T_ego, p)  # where the points land if they are static
    ego_dist, ego_plane = ego_surface
    static_score = _fit(ego_plane, c)
    static_fitness, static_rmse = static_score
    record = {"points": int(len(p)), "static_fitness": static_fitness, "static_rmse_m": static_rmse,
              "accepted": False}
    fits = (static_fitness >= c.static_fitness_accept and static_rmse <= c.static_accept_rmse_m
            and np.count_nonzero(sub) < c.static_accept_max_movers * len(p))
    hidden = (not fits and range_image is not None and c.hidden_test and not sub.any() and not seen.any()
              and _static_where_hidden(ego, ego_plane, p + flow, range_image, guesses, c))
    few_rings = not (fits or hidden) and ring_slice is not None and ring_slice()
    if fits or hidden or few_rings:  # static: skip the ICP
        record["hidden"] = hidden
        if few_rings:
            record["few_rings"] = True
        record.update(accepted=True, speed_mps=0.0,
                      result=(ego, np.zeros(len(p), dtype=bool), np.full(len(p), -1, dtype=np.int64)))
        return record
    R = T_ego[:3, :3]
    T0 = _displacement_start(p, flow, T_ego)  # the network's (or carried) displacement
    mover_starts = _mover_starts(p, sub, seen, T_ego, c)
    reach = max(abs(d) for d in c.hypotheses_m) if mover_starts else 0.0
    box = _target_box(surface, transform_points(T0, p), ego, reach, c)
    record["target_points"] = int(len(box))
    if len(box) < c.min_points:
        return record
    tgt = IcpTarget(box)
    motions = []  # candidate rigid motions of (parts of) this object besides the ego motion
    q = p[_icp_subset(len(p), c)]  # the points its ICP registers
    T, fitness, rmse, T_start = _best_icp(q, tgt, surface, [T0] + mover_starts, T_ego, c,
                                          prefer_first=c.prefer_first_start)
    moved_by = float(np.linalg.norm((T[:3, :3] - R) @ p.mean(axis=0) + T[:3, 3] - T_start[:3, 3]))
    record.update(fitness=fitness, rmse_m=rmse, icp_correction_m=moved_by)
    if fitness >= c.min_fitness and rmse <= c.max_rmse_m and moved_by <= c.max_correction_m:
        record["accepted"] = True
        if not _ego_explains(static_score, fitness, rmse, min(len(p), c.max_icp_points), c):
            motions.append(_polished(q, box, T, fitness, rmse, surface, T_ego, c))
    whole = motions[:1]  # the object's whole-body motion, when it has one
    if mover_starts:
        for part, starts in _mover_parts(p[sub], mover_starts, T_ego, c):
            moving_part = part[_icp_subset(len(part), c)]
            joint_on_movers = _score(moving_part, motions[0], surface, c)[0] if motions else 0.0
            # the geometric movers alone, from shifted ego landings -- only when the object's own ICP
            # does not already explain them (no fitness, at most 1, can then beat its by static_preference)
            if joint_on_movers + c.static_preference >= 1.0:
                continue
            Tm, fm, rm, _ = _best_icp(moving_part, tgt, surface, starts + [T0], T_ego, c, prefer_first=False)
            record.update(mover_fitness=fm, mover_rmse_m=rm)
            if fm >= c.min_fitness and rm <= c.max_rmse_m and fm > joint_on_movers + c.static_preference:
                record["accepted"] = True
                motions.append(_polished(moving_part, box, Tm, fm, rm, surface, T_ego, c))
    if whole and len(motions) > 1 and _slow_and_needless(p, ego, ego_plane, whole[0], motions[1:], surface, c):
        motions = motions[1:]
        record["whole_motion_dropped"] = True
    if motions and c.leftover_motion:
        leftover = _leftover_motion(p, flow, ego_plane, motions, tgt, surface, T_ego, c)
        if leftover is not None:
            motions.append(leftover)
            record["leftover_motion"] = True
    if motions and c.min_discriminating_share > 0 and np.count_nonzero(seen) < max(c.min_seen_through,
                                                                                SEEN_EVIDENCE_SHARE * len(p)):
        kept = _observable_motions(p, ego, motions, interval, surface, c)
        if len(kept) < len(motions):
            record["unobservable_motions"] = len(motions) - len(kept)
        motions = kept
    if not motions and older is not None and c.slide_free_share > 0:
        slid = _slid(p, solid, ego_plane, T_ego, older, surface, c)
        if slid is not None:
            motions.append(slid)
            record.update(accepted=True, slid=True)
    if record["accepted"]:
        if motions:
            record["motion"] = motions[0]
        landing, which = _choose_landing(p, ego, motions, surface, c, solid, ego_dist)
        moving = _moving(landing, ego, interval, c)
        record["speed_mps"] = 0.0  # a moving object's: :func:`_split_instances`, from its final flow
        record["result"] = (np.where(moving[:, None], landing, ego), moving, which)
    return record


def _slid(p: np.ndarray, solid: np.ndarray | None, ego_plane: np.ndarray, T_ego: np.ndarray, older: OlderView,
          surface: ScanSurface, c: ObjectRefinementConfig) -> np.ndarray | None:
    """``slide_free_share``: the slide motion (:func:`~flowslam.sceneflow.refinement.slide.slide_motion`)
    of an object (points ``p``, frame k-1; ``solid``: those clear of the ground, None: all;
    ``ego_plane``: the :func:`_plane_distances` of their ego landings, the object's static score)
    wider than ``PERSON_MAX_EXTENT_M``, at least ``slide_min_range_m`` away and on at least
    ``slide_min_rings`` of the sensor's rings, along the
    principal axis of its solid points, scored on scan k by :func:`_score`; None without one."""
    body = p if solid is None else p[solid]
    if len(body) < c.min_points or np.hypot(*np.ptp(body[:, :2], axis=0)) <= PERSON_MAX_EXTENT_M:
        return None
    if np.hypot(*body[:, :2].mean(axis=0)) < c.slide_min_range_m:
        return None
    if c.slide_min_rings > 1 and ring_count(body, c.ring_gap_rad) < c.slide_min_rings:
        return None
    static_fitness = _fit(ego_plane if solid is None else ego_plane[solid], c)[0]
    return slide_motion(body, _principal_axis(body), T_ego, older, lambda T: _score(body, T, surface, c),
                        static_fitness, c)


def _slow_and_needless(p: np.ndarray, ego: np.ndarray, ego_plane: np.ndarray, whole: np.ndarray,
                       movers: list[np.ndarray], surface: ScanSurface, c: ObjectRefinementConfig) -> bool:
    """``whole_motion_slow_share``: whether an object's whole-body motion ``whole`` moves
    its points ``p`` (frame k-1; ``ego`` their ego landings, frame k) by at most that share
    of the slowest of its ``movers``' motions (mean horizontal departure) and lands no more
    of them on scan k's surface than the ego motion and those motions (:func:`_adds_fit`)."""
    if c.whole_motion_slow_share <= 0:
        return False
    departure = [float(np.linalg.norm((transform_points(M, p) - ego)[:, :2].mean(axis=0))) for M in [whole] + movers]
    if departure[0] > c.whole_motion_slow_share * min(departure[1:]):
        return False
    return not _adds_fit(p, ego_plane, whole, movers, surface, c)


def _adds_fit(p: np.ndarray, ego_plane: np.ndarray, motion: np.ndarray, others: list[np.ndarray],
              surface: ScanSurface, c: ObjectRefinementConfig) -> bool:
    """Whether ``motion`` lands more of an object's points ``p`` (frame k-1) within
    ``score_plane_m`` of scan k's surface than the ego motion (``ego_plane``: its landings'
    :func:`_plane_distances`) and the ``others`` motions together (:func:`_landed`: a
    point counts when any of them lands it), by more than :func:`_fitness_margin`."""
    base = _landed(p, ego_plane, others, surface, c)
    fitness = np.count_nonzero(base) / len(p)
    by_motion = _plane_distances(transform_points(motion, p), surface, c) < c.score_plane_m
    more = np.count_nonzero(base | by_motion) / len(p)
    return more > fitness + _fitness_margin(fitness, len(p), c)


def _landed(p: np.ndarray, ego_plane: np.ndarray, motions: list[np.ndarray], surface: ScanSurface,
            c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: the points ``p`` (frame k-1) that the ego motion (``ego_plane``: the
    :func:`_plane_distances` of their ego landings) or one of ``motions`` lands within
    ``score_plane_m`` of scan k's surface."""
    on = ego_plane < c.score_plane_m
    for M in motions:
        on |= _plane_distances(transform_points(M, p), surface, c) < c.score_plane_m
    return on


SEEN_EVIDENCE_SHARE = 0.02
"""An object has free-space evidence of motion (:func:`_observable` does not apply) when at
least this share of its points (and ``min_seen_through``) are seen through: a few such
points of a long wall are its edges, not a trail."""


DISCRIMINATING_COS = 0.5
"""A landing discriminates a motion from the ego motion when its surface normal in scan k
lies within 60 degrees of the motion's direction (|cos| at least this)."""


WALKER_MAX_SPEED_MPS = 3.0
"""A walker-sized object (``FOOTPRINT_MAX_EXTENT_M``) moving at most this fast (m/s) keeps its
motion without :func:`_observable`: a walker beside a fence forms one small object with it,
whose motion the fence's normals cannot judge; faster, it is no walker."""


def _observable_motions(p: np.ndarray, ego: np.ndarray, motions: list[np.ndarray], interval: float,
                        surface: ScanSurface, c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The ``motions`` of an object (points ``p``, frame k-1; ``ego`` their ego landings)
    that scan k can tell from the ego motion (:func:`_observable`), and those of a
    walker-sized object (``FOOTPRINT_MAX_EXTENT_M``) at most ``WALKER_MAX_SPEED_MPS`` fast
    (``interval``: the scan interval, s)."""
    walker = np.hypot(*np.ptp(p[:, :2], axis=0)) <= FOOTPRINT_MAX_EXTENT_M
    kept = []
    for M in motions:
        landing = transform_points(M, p)
        departure = (landing - ego).mean(axis=0)  # m per scan, frame k
        walking = walker and np.linalg.norm(departure) <= WALKER_MAX_SPEED_MPS * interval
        if walking or _observable(landing, departure, surface, c):
            kept.append(M)
    return kept


def _observable(landing: np.ndarray, departure: np.ndarray, surface: ScanSurface, c: ObjectRefinementConfig) -> bool:
    """Whether scan k can tell a motion of an object from the ego motion, given the motion's
    ``landing`` of its points ((M,3), frame k) and their mean ``departure`` (3,) from the ego
    landings (m): at least ``min_discriminating_share`` of the landings lie at a scan-k point
    (within ``score_distance_m``) whose surface normal is within 60 degrees of the departure
    (``DISCRIMINATING_COS``). A wall or a fence slid along itself fits scan k anywhere along
    the slide: every normal there is across the motion, and the slide's fit says nothing
    (the KITTI double wall; simulated fences). A car moving forward shows its front or back."""
    length = float(np.linalg.norm(departure))
    if length == 0.0:
        return False
    _, ok, _, normals = _nearest_normals(landing, surface, c)
    if ok.size == 0:
        return False
    cos = np.abs(normals @ (departure / length))
    known = np.isfinite(cos)  # a landing at a line (a sparse ring) has no normal: it tells nothing
    if np.count_nonzero(known) < c.min_points:
        return True
    return np.count_nonzero(cos[known] >= DISCRIMINATING_COS) >= c.min_discriminating_share * np.count_nonzero(known)


def _leftover_motion(p: np.ndarray, flow: np.ndarray, ego_plane: np.ndarray, motions: list[np.ndarray],
                     tgt: IcpTarget, surface: ScanSurface, T_ego: np.ndarray,
                     c: ObjectRefinementConfig) -> np.ndarray | None:
    """A further rigid motion for the points of an object (``p``, frame k-1; ``flow`` their
    input flow, ``ego_plane`` the :func:`_plane_distances` of their ego landings; ``tgt``:
    its target box) that neither the ego
    motion nor any of its ``motions`` lands on scan k's surface (within ``score_plane_m``), when they are at least
    ``min_points`` and ``leftover_share`` of it: registered on their own from their input
    flow's median displacement, kept when it fits (``min_fitness``, ``max_rmse_m``) and the
    ego motion does not explain them as well. Two vehicles side by side that move apart
    form one cluster, and one motion registers only one of them."""
    left = ~_landed(p, ego_plane, motions, surface, c)
    if left.sum() < max(c.min_points, c.leftover_share * len(p)):
        return None
    r = p[left][_icp_subset(int(left.sum()), c)]
    T0 = _displacement_start(p[left], flow[left], T_ego)
    T, fitness, rmse, _ = _best_icp(r, tgt, surface, [T0], T_ego, c)
    if fitness < c.min_fitness or rmse > c.max_rmse_m:
        return None
    if _ego_explains(_score(r, T_ego, surface, c), fitness, rmse, len(r), c):
        return None
    return _polished(r, tgt.points, T, fitness, rmse, surface, T_ego, c)


def _split_instances(source: np.ndarray, flow: np.ndarray, moving: np.ndarray, instance: np.ndarray,
                     motion_of: np.ndarray, objects: list[dict], T_ego: np.ndarray, interval: float,
                     surface: ScanSurface, c: ObjectRefinementConfig, range_image=None,
                     seen: np.ndarray | None = None, above_ground: np.ndarray | None = None, *,
                     ego_landings: _EgoLandings) -> np.ndarray:
    """Split every object's ``moving`` points into instances (:func:`_parts`: by the motion
    they took, ``motion_of``, then by ``instance_cell_m`` components, and with ``above_ground``
    (scan k-1's points clear of the ground) apart where only their low points touch); part 0 keeps the
    object's entry and ``instance`` id, each further part gets a new entry (``part_of``)
    appended to ``objects``. A part (part 0 too) that the ego motion explains as well as
    its own landings do (:func:`_ego_explains` on scan k's ``surface``, with
    ``part_rmse_ratio``) stays static: a
    parked car merged into a passing truck's cluster, or a hedge merged with a walker,
    slides along itself under the other's motion. A moving part also loses the pieces of
    it that the ego motion fits more tightly (:func:`_still_pieces`, ``still_piece_rmse_m``):
    a stopped car beside a passing one, which slides along itself under its motion.
    Returns the points of such parts and pieces (static; they keep the object's
    ``instance``). With ``range_image`` (scan k's), a part
    with fewer than ``min_seen_through`` ``seen`` points is compared on its visible ego
    landings only (``split_visible``). A moving part holding several people (``split_people``,
    :func:`_people`) becomes one instance per person. Speeds (m/s) are the parts' median
    departure from the ego landing (``flow`` against ``T_ego``'s) over ``interval`` s
    (0 for an object whose part 0 stays static). ``ego_landings``: the round's."""
    still = np.zeros(len(source), dtype=bool)
    idx = np.flatnonzero(moving & (instance >= 0))
    if idx.size == 0:
        return still
    ego = transform_points(T_ego, source[idx])
    departure = np.linalg.norm(source[idx] + flow[idx] - ego, axis=1) / interval
    for members in _runs(instance[idx]):
        own = int(instance[idx[members[0]]])
        parts = _parts(source[idx[members]], motion_of[idx[members]], c,
                       None if above_ground is None else above_ground[idx[members]])
        objects[own]["speed_mps"] = 0.0
        for part in range(int(parts.max()) + 1):
            sel = members[parts == part]
            mine = idx[sel]
            landing = source[mine] + flow[mine]
            ego_plane, own_plane = ego_landings(mine)[1], _plane_distances(landing, surface, c)
            planes = ego_plane, own_plane  # of all the part's points, for its pieces
            if range_image is not None and np.count_nonzero(seen[mine]) < c.min_seen_through:
                # ego landings hidden behind something other than the part's own new surface
                # count for neither side: scan k cannot tell where those points went
                visible = _visible(ego[sel], ego_plane, landing, range_image, c)
                ego_plane, own_plane = ego_plane[visible], own_plane[visible]
            landed = _fit(own_plane, c)
            if len(own_plane) and _ego_explains(_fit(ego_plane, c), *landed, len(own_plane), c, c.part_rmse_ratio):
                still[mine] = True
                continue
            quiet = (_still_pieces(source[mine], above_ground[mine], *planes, c)
                     if c.still_piece_rmse_m > 0 and above_ground is not None else None)
            if quiet is not None and quiet.any():
                still[mine[quiet]] = True
                sel, mine = sel[~quiet], mine[~quiet]
                if not len(mine):
                    continue
            # a moving part is one instance, or one per person (a crowd); the people split
            # only numbers instances, it decides nothing about motion
            for g, group in enumerate(_per_person(source[mine], c)):
                speed = float(np.median(departure[sel[group]]))
                if part == 0 and g == 0:
                    objects[own]["speed_mps"] = speed
                    continue
                instance[mine[group]] = len(objects)
                objects.append({"points": int(len(group)), "part_of": own, "accepted": True, "speed_mps": speed})
    return still


def _still_pieces(p: np.ndarray, high: np.ndarray, ego_plane: np.ndarray, own_plane: np.ndarray,
                  c: ObjectRefinementConfig) -> np.ndarray:
    """(M,) bool: the points of a moving part ``p`` (frame k-1; ``high``: clear of the
    ground; ``ego_plane`` / ``own_plane``: :func:`_plane_distances` of their ego landings and
    of their own) in pieces that the ego motion explains (``still_piece_rmse_m``): the
    part's high points as ``instance_cell_m`` components joined across its gap, each low
    point in the piece of its nearest high point; only where there are two pieces or more."""
    quiet = np.zeros(len(p), dtype=bool)
    hi = np.flatnonzero(high)
    if hi.size < c.min_points:
        return quiet
    labels, big = _joined_components(p[hi], c, _instance_gap(p, c))
    if len(big) < 2:
        return quiet
    piece = _nearest_labels(p, hi, labels)
    for b in big:
        mine = piece == b
        ego_fitness, ego_rmse = _fit(ego_plane[mine], c)
        own_fitness, own_rmse = _fit(own_plane[mine], c)
        if (ego_rmse <= min(own_rmse, c.still_piece_rmse_m)
                and ego_fitness >= own_fitness - _fitness_margin(own_fitness, int(mine.sum()), c)):
            quiet |= mine
    return quiet


def _instance_gap(p: np.ndarray, c: ObjectRefinementConfig) -> float:
    """The distance (m) across which BEV components of the points ``p`` (one motion's) join:
    ``instance_gap_rad`` times their median horizontal range."""
    return c.instance_gap_rad * float(np.median(np.hypot(p[:, 0], p[:, 1])))


def _nearest_labels(p: np.ndarray, idx: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(M,) the label of each point of ``p`` (M,3): that of its nearest (BEV) point among
    ``p[idx]``, which carry ``labels`` (len(idx),)."""
    from scipy.spatial import cKDTree

    return labels[cKDTree(p[idx, :2]).query(p[:, :2])[1]]


def _runs(keys: np.ndarray) -> list[np.ndarray]:
    """Positions of ``keys`` (M,) int grouped by key, in key order, each group in
    ascending position order."""
    order = np.argsort(keys, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(keys[order])) + 1)


def _per_person(p: np.ndarray, c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The moving points ``p`` (M,3) of one part as its instances (index arrays): one per
    person with ``split_people`` (:func:`_people`), else all in one."""
    return _people(p, c) if c.split_people else [np.arange(len(p))]


def _number_unregistered(source: np.ndarray, flow: np.ndarray, dynamic: np.ndarray, instance: np.ndarray,
                         objects: list[dict], T_ego: np.ndarray, interval: float, above_ground: np.ndarray | None,
                         c: ObjectRefinementConfig) -> int:
    """``unregistered_instances``: the ``dynamic`` points of ``source`` (frame k-1; the
    caller leaves out those within ``min_range_m``, the ego vehicle's body, which moves with
    the sensor) that no accepted entry of ``objects`` holds get instances of their own
    (``instance`` and ``objects`` updated in place; each new entry has ``unregistered:
    True``, ``accepted: False`` (no registration of it was accepted) and its speed, the
    median departure (m/s) of its landings ``source + flow`` from the ego landings over
    ``interval`` s): grouped by the object they were registered in, or, outside every
    object, by ``cluster_cell_m`` BEV clusters; then split as :func:`_split_instances`
    splits a moving object (:func:`_parts` with ``above_ground``, :func:`_per_person`); an
    instance needs ``min_points`` points (smaller fragments stay dynamic without one).
    Returns the number of new instances."""
    accepted = np.array([o["accepted"] for o in objects] + [False])  # instance -1 -> False
    idx = np.flatnonzero(dynamic & ~accepted[instance])
    if idx.size == 0:
        return 0
    group = _rest_groups(source, idx, instance, len(objects), c)
    departure = np.linalg.norm(source[idx] + flow[idx] - transform_points(T_ego, source[idx]), axis=1) / interval
    first = len(objects)
    for members in _runs(group):
        parts = _parts(source[idx[members]], np.zeros(len(members), dtype=np.int64), c,
                       None if above_ground is None else above_ground[idx[members]])
        for part in range(int(parts.max()) + 1):
            sel = members[parts == part]
            for person in _per_person(source[idx[sel]], c):
                if len(person) < c.min_points:  # a fragment: dynamic, but no object
                    continue
                instance[idx[sel[person]]] = len(objects)
                objects.append({"points": int(len(person)), "accepted": False, "unregistered": True,
                                "speed_mps": float(np.median(departure[sel[person]]))})
    return len(objects) - first


def _rest_groups(source: np.ndarray, idx: np.ndarray, instance: np.ndarray, n_objects: int,
                 c: ObjectRefinementConfig) -> np.ndarray:
    """(len(idx),) group of each point ``idx`` of ``source`` that no accepted object holds:
    the object it was registered in (its ``instance``), or, outside every object (instance
    -1), ``n_objects`` + its ``cluster_cell_m`` BEV cluster among those."""
    group = instance[idx]
    loose = group < 0
    if loose.any():
        group[loose] = n_objects + bev_clusters(source[idx[loose]], c.cluster_cell_m)
    return group


def _slow_rest(source: np.ndarray, flow: np.ndarray, idx: np.ndarray, instance: np.ndarray, n_objects: int,
               T_ego: np.ndarray, interval: float, evidence: np.ndarray, c: ObjectRefinementConfig) -> np.ndarray:
    """``rest_min_speed_mps``: those of the dynamic points ``idx`` of ``source`` (frame k-1;
    no accepted object holds them, their ego landings are off scan k's surface) whose group
    (:func:`_rest_groups`) does not move by its own flow: the median :func:`_departures` of
    its landings ``source + flow`` from the ego landings (``T_ego``) is at most
    ``rest_min_speed_mps`` over ``interval`` s, and none of its points holds geometric
    motion ``evidence`` ((N,) bool: movers or seen-through), which says it moved."""
    if idx.size == 0:
        return idx
    group = _rest_groups(source, idx, instance, n_objects, c)
    departure = _departures(source[idx] + flow[idx], transform_points(T_ego, source[idx]), c)
    slow = [members for members in _runs(group)
            if np.median(departure[members]) <= c.rest_min_speed_mps * interval and not evidence[idx[members]].any()]
    return idx[np.concatenate(slow)] if slow else idx[:0]


def _parts(p: np.ndarray, which: np.ndarray, c: ObjectRefinementConfig,
           above_ground: np.ndarray | None = None) -> np.ndarray:
    """(M,) part of each moving point of an object: grouped by the motion it took
    (``which``), each group split into BEV connected components of ``instance_cell_m``
    (joined across ``instance_gap_rad`` times the group's median range); components under
    ``min_points`` join the largest of their group. Numbered by group, then by size (part 0:
    the largest of the first motion's)."""
    parts = np.empty(len(p), dtype=np.int64)
    n = 0
    for m in np.unique(which):
        sel = np.flatnonzero(which == m)
        gap = _instance_gap(p[sel], c)
        labels, big = _joined_components(p[sel], c, gap)
        if above_ground is not None:
            labels, big = _people_apart_above_ground(p[sel], above_ground[sel], labels, big, gap, c)
        number = np.empty(int(labels.max()) + 1, dtype=np.int64)
        number[big] = n + np.arange(len(big))
        parts[sel] = number[labels]
        n += len(big)
    return parts


HEAD_CELL_M = 0.15
"""BEV cell (m) of the height map (highest point per cell) the heads are found in."""
HEAD_PROMINENCE_M = 0.12
"""A head is a cell higher than every cell within two cells of it (0.3 m: heads are
farther apart), by this much (m) than every cell exactly two cells away (shoulders and
arms): a flat top (a box, a car's roof) has no head."""
PERSON_MAX_EXTENT_M = 1.2
"""A group of people is split only when each person is at most this wide (BEV diagonal, m)."""


def _people_apart_above_ground(p: np.ndarray, high: np.ndarray, labels: np.ndarray, big: np.ndarray, gap: float,
                               c: ObjectRefinementConfig) -> tuple[np.ndarray, np.ndarray]:
    """``labels`` and ``big`` (:func:`_joined_components` of the (M,3) points ``p``), or the
    components of the points clear of the ground (``high``), each low point joined to the
    component of its nearest high point (BEV), when those are more, and each is at most
    ``PERSON_MAX_EXTENT_M`` wide: walkers whose feet, or the ground flagged between them,
    touch in BEV. A vehicle whose sparse sides part above its wheels stays whole."""
    idx = np.flatnonzero(high)
    if idx.size < c.min_points or idx.size == len(p):
        return labels, big
    labels_high, big_high = _joined_components(p[idx], c, gap)
    if len(big_high) <= len(big):
        return labels, big
    if bev_extent(p[idx, :2], labels_high, int(labels_high.max()) + 1)[big_high].max() > PERSON_MAX_EXTENT_M:
        return labels, big
    return _nearest_labels(p, idx, labels_high), big_high


def _people(p: np.ndarray, c: ObjectRefinementConfig) -> list[np.ndarray]:
    """The (M,3) moving points ``p`` (sensor frame, z up, m) of one instance as groups of
    people, one per head (index arrays, the largest first), or ``[all]``: walkers close
    together touch in BEV. Heads are local maxima of a BEV height map that stand out from
    the cells around them (:func:`_heads`); every point goes to its nearest head. Split
    only when the instance is wider than ``PERSON_MAX_EXTENT_M`` and has at least two
    heads, and either every group holds ``min_points`` points and is at most that wide, or
    the points gather around the heads (:func:`_around_heads`: a few stray points far
    off, merged static ones or a piece of something else, then make a group wider)."""
    whole = [np.arange(len(p))]
    if len(p) < 2 * c.min_points or np.hypot(*np.ptp(p[:, :2], axis=0)) <= PERSON_MAX_EXTENT_M:
        return whole
    heads = _heads(p)
    if len(heads) < 2:
        return whole
    dist2 = ((p[:, None, :2] - heads[None, :, :]) ** 2).sum(axis=2)
    near = np.argmin(dist2, axis=1)
    counts = np.bincount(near, minlength=len(heads))
    narrow = counts.min() >= c.min_points and bev_extent(p[:, :2], near, len(heads)).max() <= PERSON_MAX_EXTENT_M
    if not (narrow or _around_heads(dist2[np.arange(len(p)), near], near, len(heads), c)):
        return whole
    return [np.flatnonzero(near == h) for h in np.argsort(-counts, kind="stable")]


def _around_heads(dist2: np.ndarray, near: np.ndarray, n_heads: int, c: ObjectRefinementConfig) -> bool:
    """Whether points at squared BEV distances ``dist2`` (m^2) from their nearest head
    ``near`` (of ``n_heads``) gather around the heads: at least ``people_core_share`` of
    them lie within half a person's width (``PERSON_MAX_EXTENT_M`` / 2) of it, and each head
    has ``min_points`` such points. A vehicle's points spread over its length (measured on
    simulated vehicles with two height peaks: 90 % of them have at most 0.43 of their
    points that near, and none passed both tests)."""
    if c.people_core_share > 1:
        return False
    core = dist2 <= (PERSON_MAX_EXTENT_M / 2) ** 2
    return bool(core.mean() >= c.people_core_share and np.bincount(near[core], minlength=n_heads).min() >= c.min_points)


def _heads(q: np.ndarray) -> np.ndarray:
    """(H,2) BEV positions of the heads among the (M,3) points ``q``
    (``HEAD_CELL_M``, ``HEAD_PROMINENCE_M``)."""
    from scipy.ndimage import maximum_filter

    lo = q[:, :2].min(axis=0)
    ij = np.floor((q[:, :2] - lo) / HEAD_CELL_M).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 1)
    ids = ij[:, 0] * shape[1] + ij[:, 1]
    height = -lowest_per_cell(ids, -q[:, 2], shape[0] * shape[1]).reshape(shape)  # highest z per cell, -inf: none
    ring = np.ones((5, 5), dtype=bool)
    ring[1:4, 1:4] = False
    near = maximum_filter(height, size=5, mode="constant", cval=-np.inf)
    around = maximum_filter(height, footprint=ring, mode="constant", cval=-np.inf)
    standing = np.isfinite(around) & (height - np.where(np.isfinite(around), around, 0.0) >= HEAD_PROMINENCE_M)
    cells = np.argwhere(np.isfinite(height) & (height == near) & standing)
    kept: list[np.ndarray] = []  # one per head: a head across two cells ties with itself
    for cell in cells[np.argsort(-height[tuple(cells.T)], kind="stable")]:
        if all(np.abs(cell - k).max() > 2 for k in kept):
            kept.append(cell)
    heads = []
    for cell in kept:  # the centroid of the head: its points within 0.1 m of its top
        top = (np.abs(ij - cell).max(axis=1) <= 1) & (q[:, 2] >= height[tuple(cell)] - 0.1)
        heads.append(q[top, :2].mean(axis=0))
    return np.array(heads).reshape(-1, 2)


def _joined_components(p: np.ndarray, c: ObjectRefinementConfig,
                       gap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """BEV connected components of ``instance_cell_m`` of the (M,3) points ``p`` (m), also
    joined where their points come within ``gap`` (m; only when wider than the cell): (M,)
    the component of each point, where those under ``min_points`` have joined the largest,
    and the labels of the components kept, largest first (the largest alone when none has
    ``min_points``)."""
    labels = bev_clusters(p, c.instance_cell_m)
    if gap > c.instance_cell_m:
        labels = joined_labels(p[:, :2], labels, gap)  # components with points within gap merged
    counts = np.bincount(labels)
    order = np.argsort(-counts, kind="stable")
    big = order[counts[order] >= c.min_points]
    if big.size == 0:
        big = order[:1]
    return np.where(np.isin(labels, big), labels, big[0]), big


def _on_own_surface(ego: np.ndarray, landing: np.ndarray, kept: np.ndarray, solid: np.ndarray,
                    radius: float) -> np.ndarray:
    """(M,) bool: which ``solid`` points have their ego landing ``ego`` (M,3, frame k) within
    ``radius`` (m) of the landing of a point that keeps the object's motion (``kept``,
    on scan k's surface there): the ego landing is on the object itself, where it is now."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(ego), dtype=bool)
    ask = np.flatnonzero(solid & ~kept)
    if ask.size and kept.any():
        out[ask] = np.isfinite(cKDTree(landing[kept]).query(ego[ask], distance_upper_bound=radius)[0])
    return out


def _part_majority(p: np.ndarray, best: np.ndarray, dist: np.ndarray, solid: np.ndarray,
                   c: ObjectRefinementConfig) -> np.ndarray:
    """``best`` (M,), each point's motion, with each ``solid`` point (clear of the ground)
    given the motion that most points of its ``instance_cell_m`` BEV component took among
    those that only one motion lands on scan k's surface (``dist`` (K,M): each motion's
    landing's distance to scan k, inf beyond ``score_distance_m`` or for a motion that lifts
    the point), when that motion lands it near scan k's points too: a car's roof and sides fit
    a neighbouring car's motion as well, sliding along themselves, and only its ends tell."""
    on = dist <= c.score_plane_m
    idx = np.flatnonzero(solid)
    if idx.size == 0:
        return best
    labels = bev_clusters(p[idx], c.instance_cell_m)
    mine = best[idx]
    voted = on[mine, idx] & (on[:, idx].sum(axis=0) == 1)  # only one motion explains them: they tell
    votes = np.zeros((int(labels.max()) + 1, on.shape[0]))
    np.add.at(votes, (labels[voted], mine[voted]), 1.0)
    major = votes.argmax(axis=1)[labels]
    take = np.isfinite(dist[major, idx]) & (votes.sum(axis=1)[labels] > 0)
    best = best.copy()
    best[idx[take]] = major[take]
    return best


def _choose_landing(p: np.ndarray, ego: np.ndarray, motions: list[np.ndarray], surface: ScanSurface,
                    c: ObjectRefinementConfig, solid: np.ndarray | None = None,
                    ego_dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(M,3) landing of each point of ``p`` (frame k) and (M,) the index of the motion it
    took (-1: the ego motion): the landing of the object motion that
    puts it nearest to scan k's surface (the first when none lands within
    ``score_distance_m``), unless that leaves it off the surface (no scan point within
    ``score_plane_m``) while its ego landing ``ego`` is strictly nearer: then the ego
    landing. Points the object's motion explains keep it (an object is rigid: the faces a
    car slides along explain its ego landings too, and must not split it); the others are
    the static false positives merged into the object. A motion that moves a point up or
    down from its ego landing by more than ``vertical_margin_m`` + ``vertical_grade`` x
    its horizontal departure is not one of its choices (an object's motion passes that
    test at its centroid, but a turn of a long or merged object can lift its far end):
    with no motion left, the point takes its ego landing. With ``own_surface_m`` > 0 and
    ``solid`` (M,) bool (points clear of scan k-1's local ground), a solid point whose ego
    landing lies on the object's own new surface (:func:`_on_own_surface`) keeps its
    motion: a vehicle that slid along itself puts its rear points' ego landings onto its
    own side, which explains them no better than its motion. ``ego_dist``: the ego
    landings' distances to scan k (:func:`_surface_distances`), when known."""
    if not motions:
        return ego, np.full(len(p), -1, dtype=np.int64)
    landings = np.stack([transform_points(M, p) for M in motions])
    dist = surface.nearest(landings.reshape(-1, 3), c.score_distance_m)[0]
    dist = dist.reshape(len(motions), len(p))
    lifted = _lifted(landings - ego, c)
    no_motion = lifted.all(axis=0)  # every motion lifts the point: only its ego landing is left
    dist[lifted] = np.inf  # a motion that lifts or sinks the point (a turn of a long or merged object): not its own
    best = np.argmin(dist, axis=0)
    if len(motions) > 1 and solid is not None and c.coherent_parts:
        best = _part_majority(p, best, dist, solid, c)
    rows = np.arange(len(p))
    d_ego = surface.nearest(ego, c.score_distance_m)[0] if ego_dist is None else ego_dist
    nearest = dist[best, rows]
    take_ego = ((d_ego < nearest) & ~(nearest <= c.score_plane_m)) | no_motion
    own = landings[best, rows]
    if c.own_surface_m > 0 and solid is not None:
        moved = ~take_ego & (nearest <= c.score_plane_m) & ~(d_ego <= c.score_plane_m)  # only the motion explains them
        take_ego &= ~_on_own_surface(ego, own, moved, solid & ~no_motion, c.own_surface_m)
    return np.where(take_ego[:, None], ego, own), np.where(take_ego, -1, best)
