"""Backend ``isam2``: incremental smoothing (GTSAM iSAM2) over one Pose3 per scan.

Graph
-----
- Variable ``X(index)`` (``gtsam.symbol_shorthand.X``, ``index`` = dataset frame index)
  is ``T_world_sensor`` of that scan; world = the first scan.
- A prior on the first pose at the identity (sigmas ``prior_*``).
- Odometry: ``BetweenFactorPose3(X(k-1), X(k), T_prev_curr)`` with the frontend's 6x6
  covariance (GTSAM order: rotation rad, translation m; right perturbation) under a
  Huber kernel (``huber_k``, in whitened units).
- Loops (whatever the run's loop closer finds; none in variant ``a-loam``, where
  ``loop_closure.enabled`` is false): ``BetweenFactorPose3(X(i), X(j), T_i_j)`` with the loop
  covariance under a Cauchy kernel (``cauchy_k``), followed by up to
  ``extra_iterations_after_loop`` empty iSAM2 updates (each relinearises what moved more
  than the threshold; they stop early once nothing is relinearised). A Cauchy kernel
  gives an inconsistent (false) loop a pull that *falls* with its residual, so the
  odometry chain holds; a consistent one is drawn in over the iterations. The backend
  adds every loop it is given: whether loops are searched for is not its concern.

One ``ISAM2.update`` per scan with only the new factor and the new value. The new pose
is initialised as ``latest estimate * T_prev_curr``, so a chain without loops has zero
residuals: its optimum is exactly the composition of the measurements, and ``a-loam``
reproduces the ``odometry`` backend (to ~1e-12 m after thousands of scans). Measured
rotations orthonormal only to ~1e-5 are first projected onto SO(3) (then the chain is
the composition of the projected measurements).

Relinearisation (``ISAM2Params``)
---------------------------------
A pose is relinearised when a rotation component of its linear delta exceeds
``relinearize_threshold_rad`` (default 0.02) or a translation component exceeds
``relinearize_threshold_m`` (default 1.0; per-component thresholds through GTSAM's
``ISAM2ThresholdMap``); ``relinearize_skip`` (default 1) checks every update (GTSAM's
default is every 10th). Robust-kernel weights are re-evaluated only where factors are
relinearised. ``factorization``: Cholesky (fast, GTSAM's default) or QR (more stable).
The defaults keep a loop update (with its one extra iteration) within ~50 ms on a
4,500-pose graph; the per-scan updates that follow carry on relinearising what the
loop moved (a tighter threshold or more extra iterations make the loop update itself
converge further, at 2-5x the time; ``tools/bench_backend.py`` measures it).

Final refinement
----------------
iSAM2 stops relinearising once every delta is below the thresholds, so its estimate
after loops depends slightly on the order things happened in (a few % of ATE on
KITTI-00-sized graphs). ``trajectory()`` of a graph with loops therefore polishes the
iSAM2 estimate with batch Levenberg-Marquardt over all factors (``refine_iterations``,
cached until the next update; about 0.1-0.5 s for 4,500 poses). Without loops the
graph is a chain already at its optimum and nothing is refined. ``latest_pose()``,
``estimate()`` and ``online_trajectory()`` are iSAM2's own estimate.

Indeterminate systems
---------------------
GTSAM's ``IndeterminantLinearSystemException`` reaches Python as a ``RuntimeError``
whose text starts "Indeterminate linear system detected while working near variable
... (Symbol: x12)". It leaves the ISAM2 object unusable, so the backend keeps every
accepted factor and, on such an error (or a noise model GTSAM refuses, e.g. a negative
variance), logs a warning with the frame index, records an :class:`IndeterminateEvent`
and rebuilds iSAM2 from the accepted factors at the last linearisation point plus a
repair: an odometry factor is re-added with the fallback covariance (then, if that
still fails, replaced by a weak prior at the composed guess); a loop factor is dropped.
Other errors propagate (the pipeline stops cleanly and writes what it has).

Library use
-----------
::

    backend = Isam2Backend(Isam2Config())
    backend.add_odometry(0, None, None)              # first scan: anchored at the identity
    backend.add_odometry(1, T_0_1, cov)              # each further scan
    backend.add_loop(0, 1, T_0_1_icp, cov_loop)      # a verified loop (s-loam)
    backend.latest_pose(), backend.trajectory()      # current estimates
    backend.loops, backend.events, backend.stats     # what happened
    backend.odometry_trajectory(), backend.online_trajectory()
    backend.write_g2o("graph.g2o")                   # the graph, for gtsam.readG2o / g2o

Graph export
------------
``write_g2o(path)`` (``exports_graph``: the run writes ``graph.g2o`` for backends that
have it) writes every accepted factor and, as vertices, ``trajectory()`` (the run's
final poses) with :mod:`flowslam.graph_export`: edges with the inner Gaussian model of
their robust kernel, a ``# FLOWSLAM_EDGE loop cauchy K`` / ``odometry huber K`` comment
before each, the priors as ``# FLOWSLAM_PRIOR`` comments and ``FIX`` on the first scan.
``gtsam.readG2o(path, True)`` plus a prior on the first vertex re-optimises to the run's
trajectory (exactly without loops; with loops up to the Cauchy down-weighting, see
``tests/test_graph_export.py``); ``flowslam.graph_export.read_g2o`` restores the kernels.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import gtsam
import numpy as np

from flowslam import geometry, graph_export
from flowslam.config.isam2 import Isam2Config

log = logging.getLogger(__name__)

__all__ = ["Isam2Backend", "LoopRecord", "IndeterminateEvent", "make_backend"]

_WEAK_PRIOR_SIGMAS = geometry.pose_sigmas(np.pi, 1e3)
"""Last-resort prior (rad, m) on a pose whose odometry factor could not be used."""




@dataclass
class LoopRecord:
    """A loop factor added to the graph, with what it did to the estimate."""

    i: int
    j: int
    frame: int
    """Newest scan when the loop was added."""
    innovation_m: float
    innovation_deg: float
    """Disagreement of ``T_i_j`` with the estimate before the update (m, deg)."""
    residual_m: float
    residual_deg: float
    """... and after the update (a false loop kept out by the Cauchy kernel stays large)."""
    correction_m: float
    correction_deg: float
    """How far the newest pose moved through this update (m, deg)."""
    iterations: int
    """Empty updates run after the loop update."""
    seconds: float
    """Wall time of the loop update plus the extra iterations."""


@dataclass
class IndeterminateEvent:
    """An update GTSAM refused (indeterminate system or unusable noise model) and the repair."""

    frame: int
    factor: str
    """``"odometry"`` or ``"loop i-j"``."""
    variable: str | None
    """The variable GTSAM named, e.g. ``"x12"`` (None if it named none)."""
    action: str
    message: str


_INDETERMINATE = "ndeterminate linear system"  # GTSAM spells it "Indeterminate"
_SYMBOL = re.compile(r"\(Symbol: ([^)]+)\)")


class _Rejected(Exception):
    """GTSAM refused an update (indeterminate system: iSAM2 is left broken, see ``_broken``)
    or a noise model (unusable covariance: iSAM2 untouched)."""


def _key(index: int) -> int:
    return gtsam.symbol("x", int(index))


def _first_line(error: BaseException) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def _pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``inv(T_a) @ T_b``."""
    E = geometry.inv(T_a) @ T_b
    return float(geometry.translation_norm(E)), float(np.rad2deg(geometry.rotation_angle(E)))


class Isam2Backend:
    """iSAM2 pose graph (see module doc). Indices are dataset frame indices, in order."""

    name = "isam2"
    accepts_loops = True
    """The run builds a loop closer for this backend when ``loop_closure.enabled``."""
    exports_graph = True
    """The run writes ``graph.g2o`` with :meth:`write_g2o`."""

    def __init__(self, config: Isam2Config | None = None):
        self.config = config or Isam2Config()
        c = self.config
        self._params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()
        thresholds.insert(("x", geometry.pose_sigmas(c.relinearize_threshold_rad, c.relinearize_threshold_m)))
        self._params.setRelinearizeThreshold(thresholds)
        self._params.relinearizeSkip = c.relinearize_skip
        self._params.setFactorization(c.factorization.upper())
        self._params.enablePartialRelinearizationCheck = c.partial_relinearization_check
        self._isam = gtsam.ISAM2(self._params)
        self._graph = gtsam.NonlinearFactorGraph()
        """Every factor iSAM2 accepted (to rebuild it after an indeterminate system)."""
        self._huber = gtsam.noiseModel.mEstimator.Huber.Create(c.huber_k)
        self._cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(c.cauchy_k)
        self._fallback_cov = geometry.pose_covariance(
            np.deg2rad(c.fallback_rotation_sigma_deg), c.fallback_translation_sigma_m)
        self._indices: list[int] = []
        self._known: set[int] = set()
        self._latest = gtsam.Pose3()
        self._latest_matrix = np.eye(4)
        self._odometry: list[np.ndarray] = []
        self._odometry_cov: list[np.ndarray] = []
        self.loops: list[LoopRecord] = []
        """Every loop factor added, in order."""
        self._kind_of_slot: dict[int, str] = {}
        """Slots of ``_graph`` holding a map factor (``graph.g2o`` marks them)."""
        self.events: list[IndeterminateEvent] = []
        """Every update GTSAM refused, with the frame index and the repair."""
        self.update_seconds: list[float] = []
        """Wall time of each ``add_odometry`` (update + reading the new estimate)."""
        self.rebuilds = 0
        self.refine_seconds: list[float] = []
        """Wall time of each batch refinement run by ``trajectory()``."""
        self._version = 0
        """Count of successful updates (invalidates the refined trajectory)."""
        self._refined: tuple[int, np.ndarray] | None = None
        self._broken = False
        """True after a refused update: the ISAM2 object must be rebuilt before the next one."""

    # ----------------------------------------------------------------- protocol

    def add_odometry(self, index: int, T_prev_curr: np.ndarray | None, covariance: np.ndarray | None) -> None:
        """Add scan ``index`` with ``T_prev_curr`` (maps it into the previous scan) and its
        6x6 covariance; the first scan (``T_prev_curr`` ignored) is anchored at the identity."""
        start = time.perf_counter()
        index = int(index)
        if index in self._known:
            raise ValueError(f"scan {index}: already added")
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if not self._indices:
            c = self.config
            sigmas = geometry.pose_sigmas(np.deg2rad(c.prior_rotation_sigma_deg), c.prior_translation_sigma_m)
            prior = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            graph.add(gtsam.PriorFactorPose3(_key(index), gtsam.Pose3(), prior))
            values.insert(_key(index), gtsam.Pose3())
            self._update(graph, values)
            self._odometry.append(np.eye(4))
            self._odometry_cov.append(np.zeros((6, 6)))
        else:
            if T_prev_curr is None:
                raise ValueError(f"scan {index}: a relative motion is required after the first scan")
            T = self._checked_pose(T_prev_curr, f"scan {index}: T_prev_curr")
            measured = gtsam.Pose3(T)
            guess = self._latest.compose(measured)
            values.insert(_key(index), guess)
            if covariance is None:
                log.debug("scan %d: no odometry covariance, using the fallback", index)
                covariance = self._fallback_cov
            prev = self._indices[-1]
            try:
                noise = self._robust(self._huber, covariance)
                graph.add(gtsam.BetweenFactorPose3(_key(prev), _key(index), measured, noise))
                self._update(graph, values)
            except _Rejected as error:
                self._repair_odometry(index, prev, measured, guess, str(error))
            self._odometry.append(self._odometry[-1] @ T)
            self._odometry_cov.append(np.asarray(covariance, dtype=np.float64))
        self._indices.append(index)
        self._known.add(index)
        self._refresh_latest()
        self.update_seconds.append(time.perf_counter() - start)

    def add_loop(self, i: int, j: int, T_i_j: np.ndarray, covariance: np.ndarray) -> LoopRecord | None:
        """Add the constraint ``T_i_j`` (maps scan j into scan i; 6x6 covariance) between two
        added scans with a Cauchy kernel, then iterate. Returns its record (None if GTSAM refused it)."""
        i, j = int(i), int(j)
        if i == j:
            raise ValueError(f"loop {i}-{j}: a loop needs two different scans")
        T = self._checked_between(f"loop {i}-{j}", i, j, T_i_j)
        frame = self._indices[-1]
        start = time.perf_counter()
        innovation = _pose_error(self.estimate(i) @ T, self.estimate(j))
        latest_before = self._latest_matrix
        try:
            kernel = self._cauchy
            if self.config.chain_aware_loop_kernel:
                scale = self._chain_kernel_scale(i, j, np.asarray(covariance, dtype=np.float64))
                kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(self.config.cauchy_k * scale)
            noise = self._robust(kernel, covariance)
            graph = gtsam.NonlinearFactorGraph()
            graph.add(gtsam.BetweenFactorPose3(_key(i), _key(j), gtsam.Pose3(T), noise))
            self._update(graph, gtsam.Values())
        except _Rejected as error:
            self._drop(frame, f"loop {i}-{j}", error, "loop factor dropped")
            return None
        iterations = 0
        for _ in range(self.config.extra_iterations_after_loop):
            iterations += 1
            self._version += 1
            if self._isam.update().getVariablesRelinearized() == 0:
                break
        self._refresh_latest()
        residual = _pose_error(self.estimate(i) @ T, self.estimate(j))
        correction = _pose_error(latest_before, self._latest_matrix)
        record = LoopRecord(
            i, j, frame, *innovation, *residual, *correction, iterations, time.perf_counter() - start
        )
        self.loops.append(record)
        log.info(
            "iSAM2 loop %d-%d at scan %d: innovation %.2f m / %.2f deg, residual after %.2f m / %.2f deg, "
            "latest pose moved %.2f m / %.2f deg (%d iterations, %.1f ms)",
            i, j, frame, *innovation, *residual, *correction, iterations, record.seconds * 1e3,
        )
        return record

    def add_map_factor(self, i: int, j: int, T_i_j: np.ndarray, covariance: np.ndarray) -> bool:
        """Add a scan-to-map measurement ``T_i_j`` (maps scan j into anchor scan i; 6x6
        covariance, :mod:`flowslam.scan_to_map`) with the odometry's Huber kernel and update.
        Returns False if GTSAM refused it (recorded in ``events``; the graph is unchanged)."""
        i, j = int(i), int(j)
        T = self._checked_between(f"map factor {i}-{j}", i, j, T_i_j)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.BetweenFactorPose3(_key(i), _key(j), gtsam.Pose3(T), self._robust(self._huber, covariance)))
        slot = self._graph.size()
        try:
            self._rebuild(graph, gtsam.Values())
        except _Rejected as error:
            self._drop(j, f"map factor {i}-{j}", error, "map factor dropped")
            return False
        self._kind_of_slot[slot] = "map"
        self._refresh_latest()
        return True

    def chain_covariance(self, i: int, j: int) -> np.ndarray:
        """6x6 covariance of the chained odometry ``T_i_j`` (first order, right perturbation):
        sum over steps k of Ad(R_k^-1) C_k Ad(R_k^-1)^T, with R_k the motion from step k to j."""
        pos = {index: n for n, index in enumerate(self._indices)}
        a, b = sorted((pos[i], pos[j]))
        if a == b:
            return np.zeros((6, 6))
        poses = np.asarray(self._odometry[a + 1 : b + 1])
        covs = np.asarray(self._odometry_cov[a + 1 : b + 1])
        R = geometry.inv(poses) @ poses[-1]  # R_k = inv(T_w_k) T_w_b
        A = geometry.adjoint(geometry.inv(R))
        return np.einsum("kij,kjl,kml->im", A, covs, A)

    def _chain_kernel_scale(self, i: int, j: int, loop_cov: np.ndarray) -> float:
        chain = self.chain_covariance(i, j)
        ratios = [
            np.trace(chain[s, s]) / max(np.trace(loop_cov[s, s]), 1e-18)
            for s in (slice(0, 3), slice(3, 6))
        ]
        return float(min(np.sqrt(1.0 + max(ratios)), self.config.max_loop_kernel_scale))

    def latest_pose(self) -> np.ndarray:
        """Current estimate of the newest scan's ``T_world_sensor`` (cached after each update)."""
        return self._latest_matrix.copy()

    def trajectory(self) -> np.ndarray:
        """(K,4,4) ``T_world_sensor`` of every added scan: the iSAM2 estimate, refined by batch
        Levenberg-Marquardt when the graph has loops (see module doc)."""
        if not self._indices:
            return np.zeros((0, 4, 4))
        if not self.loops or self.config.refine_iterations == 0 or self._broken:
            return self.online_trajectory()
        if self._refined is None or self._refined[0] != self._version:
            self._refined = (self._version, self._refine())
        return self._refined[1].copy()

    # ----------------------------------------------------------------- extras

    @property
    def indices(self) -> list[int]:
        """Dataset indices of the added scans, in order."""
        return list(self._indices)

    def estimate(self, index: int) -> np.ndarray:
        """Current estimate of one scan's ``T_world_sensor`` (4x4)."""
        return self._isam.calculateEstimatePose3(_key(index)).matrix()

    def online_trajectory(self) -> np.ndarray:
        """(K,4,4) iSAM2's current estimate of every added scan (no batch refinement)."""
        if not self._indices:
            return np.zeros((0, 4, 4))
        try:
            values = self._isam.calculateEstimate()
        except RuntimeError as error:  # never lose the trajectory over a broken solver
            log.warning("iSAM2 estimate failed (%s); returning the linearisation point", _first_line(error))
            values = self._isam.getLinearizationPoint()
        return self._poses(values)

    def write_g2o(self, path) -> Path:
        """Write the factor graph and ``trajectory()`` as g2o (module doc, "Graph export");
        vertex ids are the dataset frame indices. Returns ``path``."""
        edges, priors = graph_export.pose_graph(self._graph, {(r.i, r.j) for r in self.loops},
                                                kind_of_slot=self._kind_of_slot)
        poses = dict(zip(self._indices, self.trajectory()))
        return graph_export.write_g2o(path, poses, edges, priors)

    def odometry_trajectory(self) -> np.ndarray:
        """(K,4,4) the odometry measurements chained from the identity (no optimisation)."""
        return np.array(self._odometry).reshape(-1, 4, 4)

    @property
    def stats(self) -> dict:
        """Counts and timings (ms) of the updates; JSON-serialisable."""
        upd = np.asarray(self.update_seconds) * 1e3
        loop = np.asarray([r.seconds for r in self.loops]) * 1e3

        def q(a: np.ndarray, p: float) -> float | None:
            return float(np.percentile(a, p)) if len(a) else None

        return {
            "scans": len(self._indices),
            "loops": len(self.loops),
            "map_factors": len(self._kind_of_slot),
            "indeterminate_events": len(self.events),
            "rebuilds": self.rebuilds,
            "median_update_ms": q(upd, 50),
            "p95_update_ms": q(upd, 95),
            "max_update_ms": q(upd, 100),
            "median_loop_update_ms": q(loop, 50),
            "max_loop_update_ms": q(loop, 100),
            "refine_ms": [t * 1e3 for t in self.refine_seconds],
            "events": [asdict(e) for e in self.events],
            "loop_records": [asdict(r) for r in self.loops],
        }

    # ----------------------------------------------------------------- internals

    @staticmethod
    def _checked_pose(T: np.ndarray, what: str) -> np.ndarray:
        """A measured transform as float64; a rotation that is orthonormal only to ~1e-5
        (float32, rounded text files) is projected onto SO(3), since GTSAM's optimum of a
        chain of such matrices is not their raw product."""
        T = np.asarray(T, dtype=np.float64)
        if not geometry.is_se3(T, tol=1e-5):
            raise ValueError(f"{what} is not a finite 4x4 rigid transform")
        R = T[:3, :3]
        return geometry.orthonormalized(T) if np.abs(R.T @ R - np.eye(3)).max() > 1e-12 else T

    def _checked_between(self, what: str, i: int, j: int, T_i_j: np.ndarray) -> np.ndarray:
        """``T_i_j`` of a factor between two added scans, checked (:meth:`_checked_pose`)."""
        for k in (i, j):
            if k not in self._known:
                raise ValueError(f"{what}: scan {k} was not added")
        return self._checked_pose(T_i_j, f"{what}: T_i_j")

    def _drop(self, frame: int, what: str, error: Exception, action: str) -> None:
        """A factor GTSAM refused: recorded (with ``action``), left out, iSAM2 rebuilt without it."""
        self._record(frame, what, str(error), action)
        self._rebuild(gtsam.NonlinearFactorGraph(), gtsam.Values())
        self._refresh_latest()

    def _robust(self, kernel, covariance: np.ndarray):
        """Robust Gaussian noise model; GTSAM's refusal (e.g. negative variance) -> _Rejected."""
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.shape != (6, 6):
            raise ValueError(f"covariance must be 6x6, got {cov.shape}")
        try:
            gaussian = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))
        except (RuntimeError, ValueError) as error:
            raise _Rejected(f"unusable covariance: {error}") from None
        return gtsam.noiseModel.Robust.Create(kernel, gaussian)

    def _update(self, graph, values) -> None:
        """One iSAM2 update; an indeterminate system raises _Rejected (iSAM2 must be rebuilt)."""
        try:
            self._isam.update(graph, values)
        except RuntimeError as error:
            if _INDETERMINATE not in str(error):
                raise
            self._broken = True
            raise _Rejected(str(error).strip()) from None
        self._graph.push_back(graph)
        self._version += 1

    def _record(self, frame: int, factor: str, message: str, action: str) -> None:
        match = _SYMBOL.search(message)
        first_line = " ".join(message.split("Thrown when")[0].split())
        event = IndeterminateEvent(frame, factor, match.group(1) if match else None, action, first_line)
        self.events.append(event)
        log.warning("iSAM2 at scan %d (%s): %s -> %s", frame, factor, first_line, action)

    def _rebuild(self, extra_graph, new_values) -> None:
        """Fresh ISAM2 from the accepted factors plus ``extra_graph`` at the last linearisation
        point (``new_values`` for keys it lacks); _Rejected if that fails too. If iSAM2 was
        not left broken (GTSAM refused a noise model), just update it."""
        if not self._broken:
            self._update(extra_graph, new_values)
            return
        theta = self._isam.getLinearizationPoint()
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self._graph)
        graph.push_back(extra_graph)
        values = gtsam.Values()
        for key in graph.keyVector():  # (iterating a temporary KeySet yields garbage keys)
            values.insert(key, theta.atPose3(key) if theta.exists(key) else new_values.atPose3(key))
        accepted = self._graph
        self._isam = gtsam.ISAM2(self._params)
        self._graph = gtsam.NonlinearFactorGraph()
        self._broken = False
        self.rebuilds += 1
        try:
            self._update(graph, values)
        except _Rejected:
            self._graph = accepted
            raise

    def _repair_odometry(self, index: int, prev: int, measured, guess, message: str) -> None:
        values = gtsam.Values()
        values.insert(_key(index), guess)
        fallback = gtsam.NonlinearFactorGraph()
        fallback.add(
            gtsam.BetweenFactorPose3(_key(prev), _key(index), measured, self._robust(self._huber, self._fallback_cov))
        )
        try:
            self._rebuild(fallback, values)
            self._record(index, "odometry", message, "odometry covariance replaced by the fallback")
            return
        except _Rejected:
            pass
        prior = gtsam.NonlinearFactorGraph()
        prior.add(gtsam.PriorFactorPose3(_key(index), guess, gtsam.noiseModel.Diagonal.Sigmas(_WEAK_PRIOR_SIGMAS)))
        self._rebuild(prior, values)  # a failure here is not a data problem: let it propagate
        self._record(index, "odometry", message, "odometry factor dropped, weak prior at the composed pose")

    def _poses(self, values) -> np.ndarray:
        return np.stack([values.atPose3(_key(k)).matrix() for k in self._indices])

    def _refine(self) -> np.ndarray:
        """Batch Levenberg-Marquardt over all accepted factors from the iSAM2 estimate."""
        start = time.perf_counter()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.config.refine_iterations)
        try:
            initial = self._isam.calculateEstimate()
            values = gtsam.LevenbergMarquardtOptimizer(self._graph, initial, params).optimize()
        except RuntimeError as error:
            log.warning("batch refinement failed (%s); keeping the iSAM2 estimate", _first_line(error))
            return self.online_trajectory()
        self.refine_seconds.append(time.perf_counter() - start)
        log.info("batch refinement of %d poses: %.0f ms", len(self._indices), self.refine_seconds[-1] * 1e3)
        return self._poses(values)

    def _refresh_latest(self) -> None:
        self._latest = self._isam.calculateEstimatePose3(_key(self._indices[-1]))
        self._latest_matrix = self._latest.matrix()


def make_backend(config) -> Isam2Backend:
    """Factory for the registry: ``config.isam2`` of a ``PipelineConfig`` (defaults if absent)."""
    return Isam2Backend(getattr(config, "isam2", None) or Isam2Config())
