"""A Pose3 factor graph as a g2o file that ``gtsam.readG2o(path, is3D=True)`` and g2o read.

Why not ``gtsam.writeG2o``: it refuses robust noise models ("invalid noise model") and
writes 6 significant digits (a vertex 1 km out keeps only centimetres, a quaternion
1e-6). This
writer emits the same two g2o records GTSAM's reader parses, at full double precision
(``repr``), and puts what g2o cannot say into comment lines, which ``readG2o`` skips.

Records (one per line)
----------------------
``VERTEX_SE3:QUAT id x y z qx qy qz qw``
    ``id`` = the scan's dataset frame index; the pose ``T_world_sensor`` (m, unit
    quaternion, w last) of the estimate given to :func:`write_g2o`.
``EDGE_SE3:QUAT i j x y z qx qy qz qw I_11 I_12 ... I_66``
    A ``BetweenFactorPose3``: the measurement ``T_i_j`` (maps scan j into scan i) and the
    21 upper-triangle entries (row by row) of the 6x6 information matrix of its Gaussian
    noise model, in g2o's order ``x y z`` (m) then rotation (rad): GTSAM's own
    ``[rotation, translation]`` tangent order swapped, exactly as ``gtsam.writeG2o`` and
    ``gtsam.readG2o`` do. For a robust factor that is the *inner* Gaussian model.
``FIX id``
    g2o's way of holding the first vertex (``readG2o`` ignores it: add a prior yourself).
``# FLOWSLAM_EDGE kind kernel k``
    Before each edge: ``kind`` is ``odometry``, ``loop`` (the loop-closure edges are
    marked here) or ``map`` (scan-to-map factors, :mod:`flowslam.scan_to_map`), ``kernel`` the robust kernel of the original factor (``huber``,
    ``cauchy``, or ``gaussian`` for none) and ``k`` its width in whitened units.
``# FLOWSLAM_PRIOR id x y z qx qy qz qw I_11 ... I_66``
    A ``PriorFactorPose3`` (the anchor of the first scan; weak priors of repaired scans),
    pose and information as for an edge.

Re-optimising: ``gtsam.readG2o`` gives the edges with their Gaussian models; with a
prior on the first vertex, Levenberg-Marquardt returns the written estimate up to the
effect of the robust kernels (none for edges whose whitened residual is below the
Huber width; a Cauchy kernel always down-weights a little). :func:`read_g2o` restores
the kernels and priors from the comments and so rebuilds the original graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import gtsam
import numpy as np

from flowslam import geometry

__all__ = ["GraphEdge", "GraphPrior", "pose_graph", "write_g2o", "read_g2o", "optimize"]

VERTEX = "VERTEX_SE3:QUAT"
EDGE = "EDGE_SE3:QUAT"
EDGE_NOTE = "# FLOWSLAM_EDGE"
PRIOR_NOTE = "# FLOWSLAM_PRIOR"

_G2O_ORDER = np.array([3, 4, 5, 0, 1, 2])
"""g2o tangent order (translation, rotation) as indices into GTSAM's (rotation, translation)."""
_UPPER = np.triu_indices(6)

_HEADER = """\
# flowslam pose graph, g2o format: gtsam.readG2o(path, is3D=True) reads it (see flowslam/graph_export.py)
# VERTEX_SE3:QUAT id x y z qx qy qz qw: id = dataset frame index, T_world_sensor (m), world = first scan
# EDGE_SE3:QUAT i j x y z qx qy qz qw + 21 information entries (upper triangle, order x y z rx ry rz):
#   T_i_j maps scan j into scan i; the Gaussian model (inside the robust kernel of the run)
# before each edge, a comment "FLOWSLAM_EDGE kind kernel k": kind odometry|loop|map, the run's kernel and width
# comments "FLOWSLAM_PRIOR id pose information": the run's priors (the first scan's anchor); FIX id: g2o's anchor
"""


@dataclass
class GraphEdge:
    """A ``BetweenFactorPose3`` of the graph, with its robust kernel spelled out."""

    i: int
    j: int
    T_i_j: np.ndarray
    """(4,4) measured transform, maps scan j into scan i (m)."""
    information: np.ndarray
    """(6,6) information of the Gaussian model, GTSAM order [rotation rad, translation m]."""
    kind: str
    """``"odometry"`` or ``"loop"``."""
    kernel: str = "gaussian"
    """``"huber"``, ``"cauchy"`` or ``"gaussian"`` (no robust kernel)."""
    kernel_k: float = 0.0
    """Kernel width in whitened units (0 for ``"gaussian"``)."""


@dataclass
class GraphPrior:
    """A ``PriorFactorPose3``: ``T_world_sensor`` of scan ``index`` with its information."""

    index: int
    T_world_sensor: np.ndarray
    information: np.ndarray
    """(6,6), GTSAM order [rotation rad, translation m]."""


# ------------------------------------------------------------------ from a GTSAM graph


def _kernel_of(model) -> tuple[str, float, object]:
    """(kernel name, width k, inner Gaussian model) of a noise model. The width is read off
    the kernel's weight function: Huber ``w(r) = k / r`` for ``r > k``; Cauchy
    ``w(r) = 1 / (1 + (r / k)^2)``, so ``k = sqrt(w(1) / (1 - w(1)))``."""
    if not isinstance(model, gtsam.noiseModel.Robust):
        return "gaussian", 0.0, model
    kernel, inner = model.robust(), model.noise()
    if isinstance(kernel, gtsam.noiseModel.mEstimator.Huber):
        r = 1e12
        return "huber", float(kernel.weight(r) * r), inner
    if isinstance(kernel, gtsam.noiseModel.mEstimator.Cauchy):
        w = float(kernel.weight(1.0))
        return "cauchy", float(np.sqrt(w / (1.0 - w))), inner
    raise ValueError(f"robust kernel {type(kernel).__name__} cannot be exported (huber and cauchy can)")


def _symbol_index(key: int) -> int:
    return int(gtsam.Symbol(key).index())


def pose_graph(
    graph: gtsam.NonlinearFactorGraph,
    loop_pairs: Iterable[tuple[int, int]] = (),
    index_of_key: Callable[[int], int] = _symbol_index,
    kind_of_slot: Mapping[int, str] | None = None,
) -> tuple[list[GraphEdge], list[GraphPrior]]:
    """The edges and priors of a graph of ``BetweenFactorPose3`` / ``PriorFactorPose3``
    (other factors raise ``ValueError``). ``index_of_key`` turns a GTSAM key into the scan
    index (default: the index of a ``gtsam.symbol``); edges whose ``(i, j)`` is in
    ``loop_pairs`` are of kind ``"loop"``, the others ``"odometry"``, unless
    ``kind_of_slot`` names the kind of the factor at that slot of ``graph`` (e.g. ``"map"``:
    a map factor can join the same two scans as an odometry factor)."""
    loops = {(int(i), int(j)) for i, j in loop_pairs}
    edges, priors = [], []
    for n in range(graph.size()):
        factor = graph.at(n)
        if factor is None:  # a removed slot
            continue
        kernel, k, gaussian = _kernel_of(factor.noiseModel())
        information = np.asarray(gaussian.information(), dtype=np.float64)
        ids = [index_of_key(key) for key in factor.keys()]
        if isinstance(factor, gtsam.BetweenFactorPose3):
            kind = (kind_of_slot or {}).get(n) or ("loop" if tuple(ids) in loops else "odometry")
            edges.append(GraphEdge(*ids, factor.measured().matrix(), information, kind, kernel, k))
        elif isinstance(factor, gtsam.PriorFactorPose3):
            priors.append(GraphPrior(ids[0], factor.prior().matrix(), information))
        else:
            raise ValueError(f"factor {n} ({type(factor).__name__}) cannot be written to g2o")
    return edges, priors


# ------------------------------------------------------------------ writing


def _numbers(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def _pose_text(T: np.ndarray) -> str:
    """``x y z qx qy qz qw`` at full precision."""
    T = np.asarray(T, dtype=np.float64)
    return _numbers(np.r_[T[:3, 3], geometry.to_quat_xyzw(T)])


def _information_text(information: np.ndarray) -> str:
    """The 21 upper-triangle entries of the information in g2o order (module doc)."""
    info = np.asarray(information, dtype=np.float64)[np.ix_(_G2O_ORDER, _G2O_ORDER)]
    return _numbers(info[_UPPER])


def g2o_lines(
    poses: Mapping[int, np.ndarray], edges: Sequence[GraphEdge], priors: Sequence[GraphPrior] = ()
) -> list[str]:
    """The lines of :func:`write_g2o` (no newlines)."""
    lines = _HEADER.splitlines()
    lines += [f"{VERTEX} {index} {_pose_text(T)}" for index, T in sorted(poses.items())]
    for e in edges:
        lines.append(f"{EDGE_NOTE} {e.kind} {e.kernel} {e.kernel_k!r}")
        lines.append(f"{EDGE} {e.i} {e.j} {_pose_text(e.T_i_j)} {_information_text(e.information)}")
    for p in priors:
        lines.append(f"{PRIOR_NOTE} {p.index} {_pose_text(p.T_world_sensor)} {_information_text(p.information)}")
    if poses:
        lines.append(f"FIX {min(poses)}")
    return lines


def write_g2o(
    path: str | Path, poses: Mapping[int, np.ndarray], edges: Sequence[GraphEdge], priors: Sequence[GraphPrior] = ()
) -> Path:
    """Write the graph (module doc): ``poses`` = ``{scan index: T_world_sensor}`` (the
    vertices' estimate, m), ``edges`` and ``priors`` from :func:`pose_graph`. Returns ``path``."""
    path = Path(path)
    path.write_text("\n".join(g2o_lines(poses, edges, priors)) + "\n")
    return path


# ------------------------------------------------------------------ reading back


def _pose_and_information(fields: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(T, information in GTSAM order) from ``x y z qx qy qz qw`` + 21 g2o information entries."""
    numbers = np.asarray(fields, dtype=np.float64)
    T = geometry.from_quat_xyzw(numbers[3:7] / np.linalg.norm(numbers[3:7]), numbers[:3])
    upper = np.zeros((6, 6))
    upper[_UPPER] = numbers[7:28]
    info_g2o = upper + np.triu(upper, 1).T
    info = np.empty((6, 6))
    info[np.ix_(_G2O_ORDER, _G2O_ORDER)] = info_g2o
    return T, info


def _notes(path: Path) -> tuple[list[tuple[int, int, str, float]], list[GraphPrior]]:
    """The flowslam comments of a file: per edge line, in order, ``(i, j, kernel, k)``
    (``"gaussian"`` where no note precedes it), and the priors."""
    kernels, priors, note = [], [], ("gaussian", 0.0)
    for line in path.read_text().splitlines():
        fields = line.split()
        if line.startswith(EDGE_NOTE):
            note = (fields[3], float(fields[4]))
        elif line.startswith(PRIOR_NOTE):
            T, info = _pose_and_information(fields[3:])
            priors.append(GraphPrior(int(fields[2]), T, info))
        elif fields and fields[0] == EDGE:
            kernels.append((int(fields[1]), int(fields[2]), *note))
            note = ("gaussian", 0.0)
    return kernels, priors


def _robust(kernel: str, k: float, gaussian):
    if kernel == "gaussian":
        return gaussian
    make = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[kernel]
    return gtsam.noiseModel.Robust.Create(make.Create(k), gaussian)


def read_g2o(path: str | Path, robust: bool = True) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """``gtsam.readG2o(path, is3D=True)`` plus the file's ``FLOWSLAM_PRIOR`` priors, and
    (``robust``) each edge wrapped again in its ``FLOWSLAM_EDGE`` kernel: the graph the
    run optimised. Keys are the scan indices (plain integers)."""
    path = Path(path)
    graph, initial = gtsam.readG2o(str(path), True)
    kernels, priors = _notes(path)
    if graph.size() != len(kernels):
        raise ValueError(f"{path}: gtsam.readG2o read {graph.size()} factors from {len(kernels)} edge lines")
    out = gtsam.NonlinearFactorGraph()
    for n, (i, j, kernel, k) in enumerate(kernels):
        factor = graph.at(n)
        if list(factor.keys()) != [i, j]:
            raise ValueError(f"{path}: factor {n} is {list(factor.keys())}, the file's edge {n} is {i}-{j}")
        model = _robust(kernel, k, factor.noiseModel()) if robust else factor.noiseModel()
        out.add(gtsam.BetweenFactorPose3(i, j, factor.measured(), model))
    for p in priors:
        out.add(gtsam.PriorFactorPose3(p.index, gtsam.Pose3(p.T_world_sensor), gtsam.noiseModel.Gaussian.Information(p.information)))
    return out, initial


def optimize(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int = 100
) -> dict[int, np.ndarray]:
    """Batch Levenberg-Marquardt from ``initial``: ``{key: T_world_sensor}`` (4x4, m)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    values = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    return {int(key): values.atPose3(key).matrix() for key in values.keys()}
