"""The ``isam2`` backend: exact chains, loops at true revisits, a false loop, indeterminate
systems, and the real KITTI extract through the pipeline (a-loam == odometry backend).

The graph tests drive the backend along the official KITTI 00 GT trajectory (4,541 poses,
3.7 km, camera-0 frame used as it is: a trajectory is a trajectory) with seeded odometry
noise whose covariance is the one given to the backend, and loop constraints at true
revisits (GT relative pose plus a little noise), one per 50 scans at most.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from pydantic import ValidationError

from flowslam import geometry
from flowslam.backends.isam2 import Isam2Backend, make_backend
from flowslam.config import Isam2Config
from flowslam.backends.odometry import OdometryBackend
from flowslam.evaluation import ape
from flowslam.interfaces import Backend
from flowslam.trajectory import read_trajectory

ODO_SIGMAS = np.array([np.deg2rad(0.05)] * 3 + [0.02] * 3)  # rad, m per scan
LOOP_NOISE = np.array([np.deg2rad(0.1)] * 3 + [0.05] * 3)
LOOP_COV = np.diag([np.deg2rad(1.0) ** 2] * 3 + [0.1**2] * 3)


def _ate(poses: np.ndarray, gt: np.ndarray) -> float:
    return float(ape(poses, gt)["rmse"])


def _scenario(gt: np.ndarray, seed: int = 0, radius_m: float = 5.0, min_gap: int = 300, every: int = 50):
    """Noisy odometry (K-1,4,4) and true loops [(i, j, T_i_j)] along a GT trajectory."""
    rng = np.random.default_rng(seed)
    rel = geometry.relative(gt[:-1], gt[1:])
    odometry = np.stack([T @ geometry.exp_se3(rng.normal(0.0, ODO_SIGMAS)) for T in rel])
    positions = gt[:, :3, 3]
    loops, last = [], -(10**9)
    for j in range(min_gap + 1, len(gt)):
        if j - last < every:
            continue
        d = np.linalg.norm(positions[: j - min_gap] - positions[j], axis=1)
        i = int(np.argmin(d))
        if d[i] < radius_m:
            loops.append((i, j, geometry.relative(gt[i], gt[j]) @ geometry.exp_se3(rng.normal(0.0, LOOP_NOISE))))
            last = j
    return odometry, loops


def _drive(backend, odometry, loops=(), covariances=None):
    """Feed the backend like the pipeline does: odometry of scan k, then the loops closing at k."""
    by_j: dict[int, list] = {}
    for loop in loops:
        by_j.setdefault(loop[1], []).append(loop)
    backend.add_odometry(0, None, None)
    cov = np.diag(ODO_SIGMAS**2)
    for k in range(1, len(odometry) + 1):
        backend.add_odometry(k, odometry[k - 1], cov if covariances is None else covariances.get(k, cov))
        for i, j, T in by_j.get(k, []):
            backend.add_loop(i, j, T, LOOP_COV)
    return backend


@pytest.fixture(scope="module")
def gt(kitti00_full_gt) -> np.ndarray:
    """The GT poses with rotations projected onto SO(3): the file's are orthonormal to ~1e-7 only."""
    poses = read_trajectory(kitti00_full_gt).poses
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    poses[:, :3, :3] = U @ Vt
    return poses


@pytest.fixture(scope="module")
def scenario(gt):
    return _scenario(gt)


@pytest.fixture(scope="module")
def s_loam(scenario):
    odometry, loops = scenario
    return _drive(Isam2Backend(Isam2Config()), odometry, loops)


# --------------------------------------------------------------------- chains


def test_chain_without_loops_is_exactly_the_composition(gt):
    odometry, _ = _scenario(gt[:1500], seed=3)
    chained = geometry.compose_relatives(odometry)
    reference = _drive(OdometryBackend(), odometry)
    for config in (Isam2Config(), Isam2Config(factorization="qr")):
        backend = _drive(Isam2Backend(config), odometry)
        assert isinstance(backend, Backend) and backend.name == "isam2"
        traj = backend.trajectory()
        assert traj.shape == (1500, 4, 4)
        assert np.abs(traj - chained).max() < 1e-6
        assert np.abs(traj - reference.trajectory()).max() < 1e-6
        np.testing.assert_allclose(backend.odometry_trajectory(), chained, atol=1e-12)
        np.testing.assert_allclose(backend.latest_pose(), traj[-1], atol=1e-12)
        assert backend.indices == list(range(1500))
        assert backend.stats["median_update_ms"] < 5.0


# --------------------------------------------------------------------- loops


def test_true_loops_cut_the_ate_of_the_odometry(gt, scenario, s_loam):
    odometry, loops = scenario
    assert len(loops) >= 10
    odo_ate = _ate(s_loam.odometry_trajectory(), gt)
    slam_ate = _ate(s_loam.trajectory(), gt)
    assert slam_ate <= 0.5 * odo_ate, (slam_ate, odo_ate)
    assert _ate(s_loam.online_trajectory(), gt) <= 0.5 * odo_ate
    assert len(s_loam.loops) == len(loops)
    final = s_loam.trajectory()
    for i, j, T in loops:  # every true loop is satisfied, none was kept out by the kernel
        dt = geometry.translation_norm(geometry.inv(final[i] @ T) @ final[j])
        assert dt < 0.5
    stats = s_loam.stats
    json.dumps(stats)
    assert stats["loops"] == len(loops) and stats["indeterminate_events"] == 0
    assert stats["median_update_ms"] < 5.0
    record = s_loam.loops[0]
    assert (record.i, record.j) == loops[0][:2] and record.innovation_m > record.residual_m


def test_loop_is_logged_with_frames_and_correction(gt, caplog):
    odometry, loops = _scenario(gt[:1700], seed=0)
    with caplog.at_level(logging.INFO, logger="flowslam.backends.isam2"):
        backend = _drive(Isam2Backend(), odometry, loops[:1])
    i, j, _ = loops[0]
    assert f"iSAM2 loop {i}-{j} at scan {j}: innovation" in caplog.text and "moved" in caplog.text
    assert backend.loops[0].correction_m > 0.1  # drift was corrected


@pytest.mark.parametrize("false_pair", [(100, 700), (3000, 4000)])
def test_a_force_accepted_false_loop_changes_the_ate_by_less_than_5_percent(gt, scenario, s_loam, false_pair):
    """A wrong match between places hundreds of metres apart, passed straight to the backend
    (as if verification had accepted it): the Cauchy kernel keeps it out."""
    odometry, loops = scenario
    i, j = false_pair
    false_T = geometry.from_euler("z", 0.1, [1.0, 0.0, -1.0])  # what ICP might report for look-alikes
    backend = _drive(Isam2Backend(Isam2Config()), odometry, loops + [(i, j, false_T)])
    base = _ate(s_loam.trajectory(), gt)
    with_false = _ate(backend.trajectory(), gt)
    assert abs(with_false - base) < 0.05 * base, (base, with_false)
    final = backend.trajectory()
    assert geometry.translation_norm(geometry.inv(final[i] @ false_T) @ final[j]) > 50.0  # not pulled in


# --------------------------------------------------------------------- indeterminate systems


@pytest.mark.parametrize(
    "bad_covariance",
    [np.zeros((6, 6)), np.diag([np.inf] + [1e-4] * 5), np.full((6, 6), np.nan), -np.eye(6), np.ones((6, 6))],
    ids=["zero", "inf", "nan", "negative", "rank-1"],
)
def test_degenerate_odometry_covariance_is_caught_with_the_frame_and_the_run_goes_on(gt, bad_covariance, caplog):
    odometry, _ = _scenario(gt[:200], seed=5)
    with caplog.at_level(logging.WARNING, logger="flowslam.backends.isam2"):
        backend = _drive(Isam2Backend(), odometry, covariances={120: bad_covariance})
    assert [(e.frame, e.factor) for e in backend.events] == [(120, "odometry")]
    event = backend.events[0]
    assert "fallback" in event.action and event.message
    assert event.variable in (None, "x119", "x120")
    assert "iSAM2 at scan 120 (odometry)" in caplog.text
    # the measurement itself was kept: still exactly the chain, all 200 scans there
    np.testing.assert_allclose(backend.trajectory(), geometry.compose_relatives(odometry), atol=1e-6)
    assert backend.stats["indeterminate_events"] == 1


def test_indeterminate_loop_is_dropped_and_reported(gt, caplog):
    odometry, _ = _scenario(gt[:300], seed=6)
    backend = _drive(Isam2Backend(), odometry)
    with caplog.at_level(logging.WARNING, logger="flowslam.backends.isam2"):
        assert backend.add_loop(10, 299, geometry.relative(gt[10], gt[299]), np.zeros((6, 6))) is None
    assert [(e.frame, e.factor, e.action) for e in backend.events] == [(299, "loop 10-299", "loop factor dropped")]
    assert "iSAM2 at scan 299 (loop 10-299)" in caplog.text
    assert backend.loops == [] and backend.rebuilds == 1
    np.testing.assert_allclose(backend.trajectory(), geometry.compose_relatives(odometry), atol=1e-6)
    backend.add_odometry(300, odometry[0], np.diag(ODO_SIGMAS**2))  # and it goes on
    assert backend.trajectory().shape == (301, 4, 4)


def test_bad_calls_raise_clear_errors():
    backend = Isam2Backend()
    backend.add_odometry(5, None, None)
    with pytest.raises(ValueError, match="relative motion is required"):
        backend.add_odometry(6, None, None)
    with pytest.raises(ValueError, match="rigid transform"):
        backend.add_odometry(6, np.full((4, 4), np.nan), np.eye(6))
    with pytest.raises(ValueError, match="already added"):
        backend.add_odometry(5, np.eye(4), np.eye(6))
    backend.add_odometry(6, np.eye(4), None)  # no covariance: the fallback one
    with pytest.raises(ValueError, match="scan 99 was not added"):
        backend.add_loop(5, 99, np.eye(4), np.eye(6))
    with pytest.raises(ValueError, match="6x6"):
        backend.add_loop(5, 6, np.eye(4), np.eye(3))
    np.testing.assert_allclose(backend.trajectory(), np.stack([np.eye(4)] * 2), atol=1e-9)


def test_config_and_factory():
    with pytest.raises(ValidationError):
        Isam2Config(bogus=1)
    with pytest.raises(ValidationError):
        Isam2Config(factorization="lu")
    cfg = Isam2Config.model_validate(Isam2Config(cauchy_k=2.0).model_dump(mode="json"))
    assert cfg.cauchy_k == 2.0

    class WithSection:
        isam2 = cfg

    assert make_backend(WithSection()).config is cfg
    assert make_backend(object()).config == Isam2Config()


# --------------------------------------------------------------------- real KITTI extract


def test_kiss_icp_a_loam_equals_the_odometry_backend_on_real_kitti(kitti_extract, tmp_path):
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.loop_closure import make_loop_closer
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_frontend
    from flowslam.run import run_sequence

    dataset = open_dataset(kitti_extract)
    config = load_config()
    odo = run_pipeline(dataset, make_frontend("kiss-icp", config), OdometryBackend())
    a_loam = run_pipeline(dataset, make_frontend("kiss-icp", config), Isam2Backend(Isam2Config()),
                          loop_closer=make_loop_closer(load_config(variant="a-loam").loop_closure))
    s_loam = run_pipeline(
        dataset, make_frontend("kiss-icp", config), Isam2Backend(Isam2Config()),
        loop_closer=make_loop_closer(config.loop_closure),
    )
    for result in (odo, a_loam, s_loam):
        assert result.error is None and result.poses.shape == (16, 4, 4)
    assert np.abs(a_loam.poses - odo.poses).max() < 1e-6
    assert s_loam.loops == [] and np.abs(s_loam.poses - odo.poses).max() < 1e-6  # 13 m: no revisit

    # by name, as `flowslam run --backend isam2 --no-mapping` does (the mapping stage adds
    # scan-to-map factors, so with it the trajectory is no longer the chain)
    outcome = run_sequence(kitti_extract, load_config(backend="isam2", output_dir=str(tmp_path),
                                                      **{"mapping.enabled": False}))
    outcome.raise_for_error()
    assert np.abs(outcome.result.poses - odo.poses).max() < 1e-6
    assert (outcome.run_dir / "trajectory_kitti.txt").exists()


def test_chain_covariance_matches_gtsam_marginals():
    """The propagated odometry covariance between two scans equals GTSAM's relative marginal."""
    import gtsam

    from flowslam import geometry

    rng = np.random.default_rng(4)
    backend = Isam2Backend(Isam2Config())
    backend.add_odometry(0, None, None)
    covs = []
    for k in range(1, 30):
        step = geometry.exp_se3(np.r_[rng.normal(0, 0.05, 3), 1.0 + rng.normal(0, 0.1), rng.normal(0, 0.2, 2)])
        L = rng.normal(size=(6, 6)) * 0.01
        cov = L @ L.T + np.diag([1e-5] * 3 + [1e-3] * 3)
        covs.append(cov)
        backend.add_odometry(k, step, cov)
    ours = backend.chain_covariance(5, 29)
    # GTSAM: batch graph with a tight prior on scan 5; the marginal of scan 29 is the relative one
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    odo = backend.odometry_trajectory()
    graph.add(gtsam.PriorFactorPose3(5, gtsam.Pose3(odo[5]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-9)))
    for k in range(5, 29):
        T = np.linalg.inv(odo[k]) @ odo[k + 1]
        graph.add(gtsam.BetweenFactorPose3(k, k + 1, gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Covariance(covs[k])))
    for k in range(5, 30):
        values.insert(k, gtsam.Pose3(odo[k]))
    theirs = gtsam.Marginals(graph, values).marginalCovariance(29)
    np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=1e-12)
