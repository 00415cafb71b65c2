"""The ``ransac`` baseline frontend (FPFH + Open3D RANSAC) on real KITTI scans, real Open3D.

The baseline is kept as published: its RANSAC pose is a 3-match hypothesis, good to a
fraction of its 0.75 m inlier distance, not to ICP's centimetres (measured on KITTI 00
frames 0-15 at the default 0.5 m voxel: 16-53 cm, 0.15-1.0 deg per pair). So the default
is held to that coarse bound and to its own covariance, and ``icp_refine`` to 5 cm / 0.5 deg
of the ICP reference.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml
from pydantic import ValidationError

from flowslam import geometry
from flowslam.config import PipelineConfig, RansacConfig, load_config
from flowslam.datasets import open_dataset
from flowslam.fallbacks import summarize_fallbacks
from flowslam.frontends.ransac import RansacFrontend, make_frontend
from flowslam.pipeline import run_pipeline
from flowslam.registry import make_backend
from flowslam.registry import make_frontend as registry_frontend
from flowslam.trajectory import read_trajectory

PAIRS = (4, 5, 6)
"""Scans k registered onto k-1."""
CHI2_6DOF_999 = 22.46
"""99.9 % quantile of chi-square with 6 degrees of freedom."""


@pytest.fixture(scope="module")
def kitti(kitti_extract):
    return open_dataset(kitti_extract), read_trajectory(kitti_extract / "reference_icp_lidar.txt").poses


@pytest.fixture(scope="module")
def features(kitti):
    """Each scan's downsampled cloud and FPFH, computed once (same voxel for every option here)."""
    dataset, _ = kitti
    frontend = RansacFrontend()
    return {k: frontend.features(dataset[k].points) for k in range(PAIRS[0] - 1, PAIRS[-1] + 1)}


def _errors(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Translation (m) and rotation (deg) error, and ``xi`` with ``T_ref = T @ Exp(xi)``."""
    xi = geometry.log_se3(geometry.inv(T) @ T_ref)
    return float(np.linalg.norm(xi[3:])), float(np.rad2deg(np.linalg.norm(xi[:3]))), xi


def _assert_covariance(cov: np.ndarray) -> None:
    assert cov.shape == (6, 6) and np.all(np.isfinite(cov))
    np.testing.assert_allclose(cov, cov.T, atol=1e-15)
    assert np.linalg.eigvalsh(cov).min() > 0


def test_ransac_and_icp_refine_recover_consecutive_kitti_motions(kitti, features):
    _, ref = kitti
    default, refined = RansacFrontend(), RansacFrontend(RansacConfig(icp_refine=True))
    for k in PAIRS:
        T_ref = geometry.relative(ref[k - 1], ref[k])  # T_prev_curr: scan k into frame k-1
        coarse = default.register(features[k], features[k - 1])
        fine = refined.register(features[k], features[k - 1])
        assert coarse.code is None and fine.code is None, (coarse.reason, fine.reason)
        assert coarse.stats["fitness"] > 0.85
        # icp_refine reports RANSAC's fitness as ``fitness`` and ICP's apart; the two calls
        # are separate RANSAC runs, and Open3D's parallel RANSAC is not bit-repeatable even
        # with the same seed (0.962 vs 0.956 seen on these pairs), hence the tolerance
        assert fine.stats["fitness"] == pytest.approx(coarse.stats["fitness"], abs=0.02)
        assert set(fine.stats["stage_ms"]) == {"ransac", "icp"}
        for r in (coarse, fine):
            _assert_covariance(r.covariance)

        et, er, xi = _errors(coarse.T_target_source, T_ref)
        assert et < default.distance_m and er < 1.5, (k, et, er)
        # the covariance owns up to the coarse pose (NEES within chi2(6) at 99.9 %)
        assert xi @ np.linalg.solve(coarse.covariance, xi) < CHI2_6DOF_999, k

        et_icp, er_icp, _ = _errors(fine.T_target_source, T_ref)
        assert et_icp < 0.05 and er_icp < 0.5, (k, et_icp, er_icp)
        assert et_icp <= et and er_icp <= er + 0.02
        assert np.all(np.diag(fine.covariance) < np.diag(coarse.covariance))


def test_global_registration_recovers_a_90_degree_30_m_jump(kitti):
    """What a local ICP cannot: FPFH + RANSAC needs no initial guess."""
    dataset, _ = kitti
    scan = dataset[0]
    T_moved = geometry.make_T(geometry.from_euler("z", 90, degrees=True)[:3, :3], [30.0, 0.0, 0.0])
    frontend = RansacFrontend()
    frontend.process(scan)
    out = frontend.process(dataclasses.replace(scan, index=1, timestamp=scan.timestamp + 0.1,
                                               points=geometry.transform_points(T_moved, scan.points)))
    assert out.stats["fallback"] is False
    et, er, _ = _errors(out.T_prev_curr, geometry.inv(T_moved))
    assert et < 0.2 and er < 0.5, (et, er)


@pytest.mark.parametrize("case", ["front-vs-back", "mirrored"])
def test_scans_that_cannot_match_give_a_counted_fallback(kitti, case):
    """No overlap (scan k-1's points ahead, scan k's behind) and a mirror image (no rigid
    motion matches; the ground plane alone still aligns ~40 % of the points): flagged,
    not a silently wrong pose."""
    dataset, _ = kitti
    a, b = dataset[0], dataset[1]
    if case == "front-vs-back":
        pa, pb = a.points[a.points[:, 0] > 15], b.points[b.points[:, 0] < -15]
    else:
        pa, pb = a.points, b.points * np.array([1.0, -1.0, 1.0])
    frontend = make_frontend(PipelineConfig())
    first = frontend.process(dataclasses.replace(a, points=pa))
    out = frontend.process(dataclasses.replace(b, points=pb))
    assert first.T_prev_curr is None and first.stats["fallback"] is False
    s = out.stats
    assert s["fallback"] is True and s["fallback_code"] == "few_inliers", s
    assert s["fitness"] < frontend.options.min_fitness and s["method"] == "constant-velocity"
    np.testing.assert_array_equal(out.T_prev_curr, np.eye(4))  # no earlier measurement: standing still
    _assert_covariance(out.covariance)
    assert np.sqrt(out.covariance[3, 3]) >= PipelineConfig().flow_odometry.no_prior_translation_std_m
    assert summarize_fallbacks([first.stats, s]) == {"frames": 2, "fallbacks": 1, "by_reason": {"few_inliers": 1}}


def test_a_scan_with_too_few_points_after_downsampling_falls_back(kitti):
    dataset, _ = kitti
    a = dataset[0]
    tiny = np.random.default_rng(0).uniform(-0.5, 0.5, (500, 3)) + [5.0, 0.0, 0.0]  # a 1 m cube: <= 27 voxels
    frontend = RansacFrontend()
    frontend.process(a)
    out = frontend.process(dataclasses.replace(a, index=1, points=tiny))
    assert out.stats["fallback"] is True and out.stats["fallback_code"] == "few_points"
    assert out.stats["stage_ms"].keys() == {"features"}  # no RANSAC was tried
    assert frontend.fallbacks == {"few_points": 1}


def test_a_run_over_the_16_kitti_frames_with_the_odometry_backend(kitti, tmp_path):
    """The plumbing, at a 1 m voxel to keep the test short (the default 0.5 m is measured
    in the report, not here)."""
    dataset, ref = kitti
    yaml_file = tmp_path / "ransac.yaml"
    yaml_file.write_text(yaml.safe_dump({"frontend": "ransac", "ransac": {"voxel_size_m": 1.0}}))
    config = load_config(yaml_file)
    assert config.ransac.voxel_size_m == 1.0 and config.ransac.icp_refine is False
    result = run_pipeline(dataset, registry_frontend(config.frontend, config), make_backend("odometry", config))
    assert result.error is None, result.error
    assert len(result.poses) == len(dataset) == 16 and len(result.odometry) == 15
    assert summarize_fallbacks(result.frontend_stats)["fallbacks"] == 0
    for stats in result.frontend_stats[1:]:
        assert stats["method"] == "ransac" and set(stats["stage_ms"]) == {"features", "ransac"}
    np.testing.assert_allclose(result.poses, geometry.compose_relatives(np.array(result.odometry)), atol=1e-9)
    distance_m = 1.5 * config.ransac.voxel_size_m
    for k, T in enumerate(result.odometry, start=1):  # each pair within the RANSAC distance
        assert _errors(T, geometry.relative(ref[k - 1], ref[k]))[0] < distance_m, k


def test_ransac_options_are_strict_and_described():
    from flowslam.config import missing_descriptions

    assert missing_descriptions(RansacConfig) == []
    assert load_config(**{"ransac.icp_refine": True}).ransac.icp_refine is True
    with pytest.raises(ValidationError):
        RansacConfig(voxel=0.3)  # unknown keys are errors
    frontend = RansacFrontend(RansacConfig(voxel_size_m=0.4))
    assert (frontend.normal_radius_m, frontend.fpfh_radius_m, frontend.distance_m, frontend.icp_distance_m) \
        == pytest.approx((0.8, 2.0, 0.6, 0.16))
