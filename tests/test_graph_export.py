"""``graph.g2o``: the iSAM2 backend's factor graph (robust factors written with their inner
Gaussian models, loop edges marked), read back by ``gtsam.readG2o`` and re-optimised to
the run's trajectory: a graph with loops built through the backend API, the real KITTI
extract (kiss-icp + isam2) and the simulated demo sequence (gt + isam2 s-loam, 4 loops).

Tolerances (measured in brackets): plain ``readG2o`` + a prior on the first vertex +
Levenberg-Marquardt matches the run's poses to 1 mm / 0.001 deg with loops (0.25 mm /
0.0005 deg on the synthetic graph, 0.03 mm on the demo: the Cauchy kernels the file can
only name in comments are gone) and to 1e-6 m without loops (exact chain);
``graph_export.read_g2o`` (kernels and priors restored) to 1e-5 m (~1e-7 m).
"""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from flowslam import geometry, graph_export
from flowslam.backends.isam2 import Isam2Backend
from flowslam.backends.odometry import OdometryBackend
from flowslam.config import Isam2Config

SIGMAS = np.array([np.deg2rad(0.2)] * 3 + [0.03] * 3)  # rad, m per scan


def _max_error(run: np.ndarray, indices, reoptimised: dict[int, np.ndarray]) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) between the run's poses and the re-optimised ones."""
    errors = [geometry.inv(T) @ reoptimised[i] for T, i in zip(run, indices)]
    return (max(float(geometry.translation_norm(E)) for E in errors),
            max(float(np.rad2deg(geometry.rotation_angle(E))) for E in errors))


def _plain_readg2o(path: Path, first: int) -> dict[int, np.ndarray]:
    """What any GTSAM user does: readG2o, a prior on the first vertex, Levenberg-Marquardt."""
    graph, initial = gtsam.readG2o(str(path), True)
    graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    return graph_export.optimize(graph, initial)


def _edge_notes(path: Path) -> list[tuple[str, str, int, int]]:
    """(kind, kernel, i, j) of each edge, from the FLOWSLAM_EDGE comment above it."""
    lines = path.read_text().splitlines()
    return [(*lines[n - 1].split()[2:4], *map(int, line.split()[1:3]))
            for n, line in enumerate(lines) if line.startswith("EDGE_SE3:QUAT")]


@pytest.fixture(scope="module")
def two_laps() -> tuple[Isam2Backend, list[int]]:
    """Two laps of a 20 m circle (scan indices from 100, as with ``--first 100``), noisy
    odometry and nine loops between the laps, through the backend API."""
    rng = np.random.default_rng(0)
    K, first = 200, 100
    angle = 4 * np.pi * np.arange(K) / K
    gt = np.stack([geometry.make_T(geometry.from_euler("z", [a])[:3, :3], [20 * np.cos(a), 20 * np.sin(a), 0.0])
                   for a in angle])
    backend = Isam2Backend(Isam2Config())
    backend.add_odometry(first, None, None)
    for k in range(1, K):
        measured = geometry.relative(gt[k - 1], gt[k]) @ geometry.exp_se3(rng.normal(0.0, SIGMAS))
        backend.add_odometry(first + k, measured, np.diag(SIGMAS**2))
        if k >= 110 and k % 10 == 0:
            T_i_j = geometry.relative(gt[k - 100], gt[k]) @ geometry.exp_se3(rng.normal(0.0, SIGMAS / 3))
            backend.add_loop(first + k - 100, first + k, T_i_j, np.diag(SIGMAS**2))
    assert len(backend.loops) == 9
    return backend, list(range(first, first + K))


def test_graph_with_loops_round_trips_through_gtsam_readg2o(two_laps, tmp_path: Path):
    backend, indices = two_laps
    path = backend.write_g2o(tmp_path / "graph.g2o")
    run = backend.trajectory()
    graph, initial = gtsam.readG2o(str(path), True)
    assert graph.size() == len(indices) - 1 + 9 and initial.size() == len(indices)
    assert sorted(initial.keys()) == indices  # vertex ids are the dataset indices
    t_m, r_deg = _max_error(run, indices, {i: initial.atPose3(i).matrix() for i in indices})
    assert t_m < 1e-9 and r_deg < 1e-9  # the vertices are the run's poses, at full precision

    t_m, r_deg = _max_error(run, indices, _plain_readg2o(path, indices[0]))
    assert t_m < 1e-3 and r_deg < 1e-3
    t_m, r_deg = _max_error(run, indices, graph_export.optimize(*graph_export.read_g2o(path)))
    assert t_m < 1e-5 and r_deg < 1e-5

    notes = _edge_notes(path)
    loops = [(i, j) for kind, kernel, i, j in notes if kind == "loop"]
    assert loops == [(r.i, r.j) for r in backend.loops]
    assert {kernel for kind, kernel, *_ in notes if kind == "loop"} == {"cauchy"}
    assert {kernel for kind, kernel, *_ in notes if kind == "odometry"} == {"huber"}
    assert f"FIX {indices[0]}" in path.read_text().splitlines()


def test_edges_carry_the_inner_gaussian_as_gtsam_writeg2o_writes_it(two_laps, tmp_path: Path):
    """Same numbers as GTSAM's own writer (6 significant digits) on the Gaussian-only graph,
    and the restored noise models are the backend's."""
    backend, indices = two_laps
    edges, priors = graph_export.pose_graph(backend._graph, {(r.i, r.j) for r in backend.loops})
    assert len(priors) == 1 and priors[0].index == indices[0]
    gaussian, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for e in edges:
        gaussian.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), gtsam.noiseModel.Gaussian.Information(e.information)))
    for i, T in zip(indices, backend.trajectory()):
        values.insert(i, gtsam.Pose3(T))
    gtsam.writeG2o(gaussian, values, str(tmp_path / "gtsam.g2o"))
    backend.write_g2o(tmp_path / "ours.g2o")

    def numbers(name: str, tag: str, q: slice) -> np.ndarray:
        """The numbers of each ``tag`` line, the quaternion (columns ``q``) with w >= 0 (q ~ -q)."""
        rows = [line.split()[1:] for line in (tmp_path / name).read_text().splitlines() if line.startswith(tag)]
        table = np.array(rows, dtype=np.float64)
        table[:, q] *= np.where(table[:, q][:, 3:] < 0, -1.0, 1.0)
        return table

    for tag, q in (("VERTEX_SE3:QUAT", slice(4, 8)), ("EDGE_SE3:QUAT", slice(5, 9))):
        theirs, ours = numbers("gtsam.g2o", tag, q), numbers("ours.g2o", tag, q)
        assert theirs.shape == ours.shape
        np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5)

    graph, _ = graph_export.read_g2o(tmp_path / "ours.g2o")
    restored, _ = graph_export.pose_graph(graph, {(r.i, r.j) for r in backend.loops}, index_of_key=int)
    for a, b in zip(edges, restored):
        assert (a.i, a.j, a.kind, a.kernel) == (b.i, b.j, b.kind, b.kernel)
        assert b.kernel_k == pytest.approx(a.kernel_k, rel=1e-9)
        np.testing.assert_allclose(b.information, a.information, rtol=1e-9)
        np.testing.assert_allclose(b.T_i_j, a.T_i_j, atol=1e-12)


def test_backends_say_whether_they_export_a_graph():
    assert Isam2Backend.exports_graph is True and OdometryBackend.exports_graph is False


def test_kitti_extract_kiss_icp_isam2_round_trip(kitti_extract, tmp_path: Path):
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_frontend

    config = load_config(backend="isam2")
    backend = Isam2Backend(config.isam2)
    result = run_pipeline(open_dataset(kitti_extract), make_frontend("kiss-icp", config), backend)
    assert result.error is None and len(result.indices) == 16
    path = backend.write_g2o(tmp_path / "graph.g2o")
    t_m, r_deg = _max_error(result.poses, result.indices, _plain_readg2o(path, result.indices[0]))
    assert t_m < 1e-6 and r_deg < 1e-6  # a chain: the optimum is the composition


def test_demo_sequence_with_loops_round_trip(tmp_path: Path):
    """The simulated demo (250 scans around a block, cached after the first use) with
    ``gt`` + isam2 + loop closure: the loops of the return to the start are marked."""
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.loop_closure import make_loop_closer
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_frontend
    from flowslam.simulation import ensure_demo_sequence

    config = load_config(backend="isam2")
    backend = Isam2Backend(config.isam2)
    result = run_pipeline(open_dataset(ensure_demo_sequence()), make_frontend("gt", config), backend,
                          loop_closer=make_loop_closer(config.loop_closure))
    assert result.error is None and len(result.loops) >= 2
    path = backend.write_g2o(tmp_path / "graph.g2o")
    assert [(i, j) for kind, _, i, j in _edge_notes(path) if kind == "loop"] == [(lc.i, lc.j) for lc in result.loops]
    t_m, r_deg = _max_error(result.poses, result.indices, _plain_readg2o(path, result.indices[0]))
    assert t_m < 1e-3 and r_deg < 1e-3
    t_m, r_deg = _max_error(result.poses, result.indices, graph_export.optimize(*graph_export.read_g2o(path)))
    assert t_m < 1e-5 and r_deg < 1e-5
