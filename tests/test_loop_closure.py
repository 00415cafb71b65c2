"""Loop closure: Scan Context descriptor and distance, candidate search, ICP verification,
Open3D's information-matrix convention, and the detector on real KITTI scans.

Real data: the KITTI 00 extract (frames 0-15, ~0.86 m apart) with the independent ICP
reference ``reference_icp_lidar.txt`` (LiDAR frame, poses relative to frame 0), and an
Argoverse 2 sweep from Pittsburgh as a place KITTI never saw.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from flowslam import geometry
from flowslam.interfaces import LoopCloser
from flowslam.config import LoopClosureConfig
from flowslam.loop_closure import make_loop_closer
from flowslam.loop_closure import scan_context as sc
from flowslam.loop_closure.candidates import CandidateIndex
from flowslam.config import ScanContextConfig, VerificationConfig
from flowslam.loop_closure.detector import ScanContextLoopCloser
from flowslam.loop_closure.verification import (
    CloudStore,
    CompactCloud,
    downsample,
    open3d_information_to_covariance,
    verify,
)
from flowslam.trajectory import read_trajectory

SECTOR_DEG = 360.0 / ScanContextConfig().sectors


def _yaw_deg(T: np.ndarray) -> float:
    return float(np.rad2deg(np.arctan2(T[1, 0], T[0, 0])))


def _angle_diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    E = geometry.inv(T_true) @ T_est
    return float(geometry.translation_norm(E)), float(np.rad2deg(geometry.rotation_angle(E)))


@pytest.fixture(scope="module")
def kitti(kitti_extract):
    from flowslam.datasets import open_dataset

    return open_dataset(kitti_extract)


@pytest.fixture(scope="module")
def reference(kitti_extract) -> np.ndarray:
    """ICP reference poses T_0_k of the extract (LiDAR frame)."""
    return read_trajectory(kitti_extract / "reference_icp_lidar.txt").poses


@pytest.fixture(scope="module")
def av2_points(av2_log) -> np.ndarray:
    from flowslam.datasets import open_dataset

    return open_dataset(av2_log)[0].points


# --------------------------------------------------------------------- Scan Context


def test_column_shift_distance_finds_the_roll():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 3, (20, 60)).astype(np.float32)
    a[:, 10:14] = 0.0  # empty columns are skipped
    d, shift = sc.distance(a, np.roll(a, -17, axis=1))
    assert d == pytest.approx(0.0, abs=1e-9) and shift == 17
    dists, shifts = sc.distances(a, np.stack([np.roll(a, 5, axis=1), rng.uniform(0, 3, (20, 60))]))
    assert shifts[0] == 60 - 5 and dists[0] < 1e-9 < 0.05 < dists[1]
    assert sc.distance(a, np.zeros_like(a))[0] == 1.0
    assert sc.shift_to_yaw(15, 60) == pytest.approx(np.pi / 2)
    assert sc.shift_to_yaw(45, 60) == pytest.approx(-np.pi / 2)


def test_descriptor_shape_max_height_and_ring_key_yaw_invariance(kitti):
    points = kitti[0].points
    cfg = ScanContextConfig()
    desc = sc.scan_context(points, cfg)
    assert desc.shape == (cfg.rings, cfg.sectors) and desc.dtype == np.float32
    assert desc.min() >= 0 and desc.max() == pytest.approx(
        points[np.hypot(points[:, 0], points[:, 1]) < cfg.max_range_m, 2].max() + cfg.height_offset_m, abs=1e-5
    )
    # an exact quarter turn of the sensor rolls the columns by 15 sectors
    quarter = np.c_[-points[:, 1], points[:, 0], points[:, 2]]
    turned = sc.scan_context(quarter, cfg)
    assert np.mean(np.isclose(turned, np.roll(desc, 15, axis=1))) > 0.99
    np.testing.assert_allclose(sc.ring_key(turned), sc.ring_key(desc), rtol=0.02, atol=0.01)


@pytest.mark.parametrize("yaw_deg", [37.0, -95.0, 170.0])
def test_rotated_and_shifted_scan_matches_itself_with_its_yaw(kitti, av2_points, yaw_deg):
    """Scan b = scan a seen from a sensor turned by yaw and moved 0.5 m: the distance is
    small, the yaw of T_a_b is found to within one sector, other places are farther."""
    points = kitti[0].points
    T_a_b = geometry.from_euler("z", yaw_deg, [0.5, 0.0, 0.0], degrees=True)
    desc_a = sc.scan_context(points)
    desc_b = sc.scan_context(geometry.transform_points(geometry.inv(T_a_b), points))
    d_same, shift = sc.distance(desc_a, desc_b)
    yaw = np.rad2deg(sc.shift_to_yaw(shift, 60))
    assert _angle_diff_deg(yaw, yaw_deg) <= SECTOR_DEG + 1e-9
    assert d_same < 0.15
    d_13m, _ = sc.distance(desc_a, sc.scan_context(kitti[15].points))  # 12.9 m down the street
    d_other, _ = sc.distance(desc_a, sc.scan_context(av2_points))  # Pittsburgh
    assert d_same < d_13m and d_same < d_other
    assert d_other > 0.3


# --------------------------------------------------------------------- candidates


def test_candidate_index_excludes_recent_frames_and_metres_and_rebuilds():
    index = CandidateIndex(exclude_recent_frames=10, exclude_recent_m=20.0, rebuild_every=5)
    keys = np.eye(40)[:, :8] + np.arange(40)[:, None] * 10.0  # distinct keys
    assert len(index.query(keys[0], 3)) == 0  # empty
    for k in range(40):
        index.add(keys[k], path_m=float(k))  # 1 m per scan: the metres rule dominates
        found = index.query(keys[k], 3)
        assert np.all(found <= k - 20) and (len(found) == 0) == (k < 20)
    assert index.eligible_count() == 20  # scans 0..19 are >= 20 m behind scan 39
    assert index.query(keys[5], 1)[0] == 5  # exact key found (tree holds it)
    assert index.query(keys[19], 1)[0] == 19  # eligible, not yet in the tree: found too
    assert 1 < index.rebuilds < 10

    still = CandidateIndex(exclude_recent_frames=10, exclude_recent_m=20.0, rebuild_every=1)
    for k in range(100):  # a car standing still: never a loop with itself
        still.add(keys[0], path_m=0.0)
    assert len(still.query(keys[0], 5)) == 0
    moving = CandidateIndex(exclude_recent_frames=10, exclude_recent_m=0.0, rebuild_every=1)
    for k in range(30):
        moving.add(keys[k % 40], path_m=0.0)
    assert moving.eligible_count() == 19  # the frames rule alone
    with pytest.raises(ValueError):
        moving.add(keys[0], path_m=-1.0)


# --------------------------------------------------------------------- verification


def test_open3d_information_is_rotation_first_left_perturbation_and_converts_to_gtsam():
    import open3d as o3d

    rng = np.random.default_rng(1)
    P = rng.uniform(-10, 10, (400, 3))
    T = geometry.from_euler("zyx", [0.4, -0.1, 0.2], [3.0, -1.0, 0.5])
    Q = geometry.transform_points(T, P)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(Q))
    info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(src, tgt, 0.05, T)
    eye = np.broadcast_to(np.eye(3), (len(P), 3, 3))
    # d/dxi of Exp(xi) q at 0 is [-hat(q), I] (xi = [omega, v]): left perturbation, target frame
    J_left = np.concatenate([-geometry.hat(Q), eye], axis=2)
    np.testing.assert_allclose(info, np.einsum("nij,nik->jk", J_left, J_left), rtol=1e-10, atol=1e-8)
    # GTSAM's right perturbation T Exp(xi): d/dxi (T Exp(xi) p) = R [-hat(p), I]
    J_right = np.einsum("ab,nbc->nac", T[:3, :3], np.concatenate([-geometry.hat(P), eye], axis=2))
    info_right = np.einsum("nij,nik->jk", J_right, J_right)
    cov = open3d_information_to_covariance(info, T, point_sigma_m=0.1)
    np.testing.assert_allclose(cov, 0.01 * np.linalg.inv(info_right), rtol=1e-8, atol=1e-14)
    # and the adjoint maps right to left perturbations: Exp(Ad xi) T == T Exp(xi)
    xi = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.3])
    np.testing.assert_allclose(geometry.exp_se3(geometry.adjoint(T) @ xi) @ T, T @ geometry.exp_se3(xi), atol=1e-12)


def test_compact_cloud_round_trip():
    p = np.random.default_rng(2).uniform(-80, 80, (1000, 3))
    c = CompactCloud(p)
    assert len(c) == 1000 and c.nbytes == 6000
    assert np.abs(c.points() - p).max() <= 0.005 + 1e-12
    with pytest.raises(ValueError):
        CompactCloud(np.array([[400.0, 0, 0]]))


def test_cloud_store_spills_to_disk_and_falls_back_to_memory(tmp_path, monkeypatch, caplog):
    """The loop closer's clouds: in an unlinked file (a few bytes a cloud in memory), read
    back exactly; without a file, or once writing fails, in memory, the spilled ones still
    readable."""
    import os

    rng = np.random.default_rng(3)
    clouds = [CompactCloud(rng.uniform(-80, 80, (n, 3))) for n in (1000, 0, 2500, 7)]
    spilled = CloudStore(directory=str(tmp_path))
    for c in clouds[:3]:
        spilled.append(c)
    assert list(tmp_path.iterdir()) == []  # unlinked: nothing left behind
    assert spilled.disk_bytes == 3500 * 6 and spilled.nbytes == 3 * 16
    with caplog.at_level(logging.WARNING):
        monkeypatch.setattr(os, "pwrite", lambda *a: (_ for _ in ()).throw(OSError(28, "No space left")))
        assert spilled.append(clouds[3]) == 3
    assert "No space left" in caplog.text and spilled.nbytes == 4 * 16 + 7 * 6
    in_memory = CloudStore(spill=False)
    for c in clouds:
        in_memory.append(c)
    for store in (spilled, in_memory):
        assert len(store) == 4
        for k, c in enumerate(clouds):
            np.testing.assert_array_equal(store.points(k), c.points())
    assert in_memory.disk_bytes == 0


def test_icp_recovers_the_reference_from_perturbed_starts(kitti, reference):
    """Frame 2 onto frame 0: the same answer from several wrong starts, within a few cm of
    the independent ICP reference (which used non-ground points and 0.2 m voxels)."""
    cfg = VerificationConfig()
    target, source = downsample(kitti[0].points, cfg), downsample(kitti[2].points, cfg)
    results = []
    for start in (
        np.eye(4),
        geometry.from_euler("z", 8.0, [1.5, -1.0, 0.0], degrees=True),
        reference[2] @ geometry.from_euler("z", -5.0, [-1.0, 0.5, 0.2], degrees=True),
    ):
        v = verify(source, target, start, cfg)
        assert v.accepted and v.fitness > 0.8 and v.inlier_rmse < cfg.max_rmse_m
        dt, dr = _errors(v.T_target_source, reference[2])
        assert dt < 0.08 and dr < 0.25
        assert np.all(np.linalg.eigvalsh(v.covariance) > 0)
        results.append(v.T_target_source)
    np.testing.assert_allclose(results[1], results[0], atol=1e-4)


def test_icp_from_descriptor_yaw_then_icp_covariance(kitti, reference):
    """The sensor of frame 2 turned by 40 deg: Scan Context's yaw starts ICP, which lands on
    the reference; the 'icp' covariance is positive definite and tighter than the floor."""
    R = geometry.from_euler("z", 40.0, degrees=True)  # T_j'_j
    turned = geometry.transform_points(R, kitti[2].points)
    truth = reference[2] @ geometry.inv(R)  # T_0_j'
    d, shift = sc.distance(sc.scan_context(turned), sc.scan_context(kitti[0].points))
    yaw = -sc.shift_to_yaw(shift, 60)  # distance(j, i) gives T_j_i; ICP wants T_i_j
    assert _angle_diff_deg(np.rad2deg(yaw), _yaw_deg(truth)) <= SECTOR_DEG
    cfg = VerificationConfig(covariance="icp")
    v = verify(downsample(turned, cfg), downsample(kitti[0].points, cfg), geometry.from_euler("z", yaw), cfg)
    assert v.accepted
    dt, dr = _errors(v.T_target_source, truth)
    assert dt < 0.08 and dr < 0.25
    fixed = verify(downsample(turned, cfg), downsample(kitti[0].points, cfg), geometry.from_euler("z", yaw))
    eig = np.linalg.eigvalsh(v.covariance - fixed.covariance)
    assert np.all(eig > 0) and eig.max() < 1e-3  # the ICP part is small and positive


def test_icp_rejects_a_wrong_pairing(kitti, av2_points):
    """A KITTI street against a Pittsburgh street: the overlap stays below the threshold."""
    cfg = VerificationConfig()
    kitti_cloud, av2_cloud = downsample(kitti[0].points, cfg), downsample(av2_points, cfg)
    for source, target in ((av2_cloud, kitti_cloud), (kitti_cloud, av2_cloud)):
        v = verify(source, target, np.eye(4), cfg)
        assert not v.accepted and v.fitness < cfg.min_fitness and "fitness" in v.reason


# --------------------------------------------------------------------- detector


def test_detector_closes_loops_on_a_revisit_with_a_turned_sensor(kitti, reference, caplog):
    """Drive frames 0,2,..,14 and come back over 15,13,..,1 with the sensor turned by 150 deg:
    every loop found pairs a return scan with a scan of the first pass, T_i_j within a few cm
    of the reference, and is logged with its frames, fitness and correction."""
    cfg = LoopClosureConfig(exclude_recent_frames=3, exclude_recent_m=4.0, cooldown_frames=0)
    closer = ScanContextLoopCloser(cfg)
    assert isinstance(closer, LoopCloser)
    R = geometry.from_euler("z", 150.0, degrees=True)
    first_pass = list(range(0, 16, 2))
    poses = {}
    loops = []
    with caplog.at_level(logging.INFO, logger="flowslam.loop_closure.detector"):
        for k in first_pass:
            poses[k] = reference[k]
            assert closer.add_scan(k, kitti[k].points, reference[k]) == []
        for n, k in enumerate(range(15, 0, -2)):
            index = 100 + n
            poses[index] = reference[k] @ geometry.inv(R)
            loops += closer.add_scan(index, geometry.transform_points(R, kitti[k].points), poses[index])
    assert len(loops) >= 3
    for loop in loops:
        assert loop.i in first_pass and loop.j >= 100
        dt, dr = _errors(loop.T_i_j, geometry.relative(poses[loop.i], poses[loop.j]))
        assert dt < 0.08 and dr < 0.25
        assert loop.fitness >= cfg.verification.min_fitness and loop.descriptor_distance <= cfg.distance_threshold
        assert loop.info["correction_m"] < 0.1  # the poses given were the reference
        assert f"loop closure {loop.i}-{loop.j}: fitness" in caplog.text
    stats = closer.stats.as_dict()
    assert stats["accepted"] == len(loops) and stats["scans"] == 16
    assert closer.memory_bytes() < 16 * 5_000  # descriptors (float16), keys, poses: ~3 kB a scan
    assert 16 * 6_000 < closer.disk_bytes() < 16 * 80_000  # the verification clouds, spilled


def test_drift_gate_rejects_a_look_alike_place_far_away(kitti, reference):
    """The same real scans seen again, but where the estimate says the car is 150 m away
    after only ~25 m of travel: a look-alike place, not a loop. With the estimate at the
    right place, the same revisit is accepted."""
    def revisit(offset_m):
        cfg = LoopClosureConfig(exclude_recent_frames=3, exclude_recent_m=4.0, cooldown_frames=0)
        closer = ScanContextLoopCloser(cfg)
        shift = geometry.make_T(t=[0.0, offset_m, 0.0])
        loops = []
        for k in range(0, 16, 2):
            closer.add_scan(k, kitti[k].points, reference[k])
        for n, k in enumerate(range(15, 0, -2)):
            loops += closer.add_scan(100 + n, kitti[k].points, shift @ reference[k])
        return loops, closer

    far, closer = revisit(150.0)
    assert far == [] and closer.stats.descriptor_hits == 0  # no candidate inside the gate
    near, _ = revisit(0.0)
    assert len(near) >= 3


def test_make_loop_closer_follows_the_variant():
    from flowslam.config import load_config

    assert make_loop_closer(LoopClosureConfig(enabled=False)) is None
    assert isinstance(make_loop_closer(LoopClosureConfig()), ScanContextLoopCloser)
    assert make_loop_closer(load_config(variant="a-loam").loop_closure) is None
    assert isinstance(make_loop_closer(load_config(variant="s-loam").loop_closure), ScanContextLoopCloser)
