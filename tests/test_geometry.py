"""SE(3) helpers: the T_a_b convention, exp/log against GTSAM, quaternion order."""

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowslam import geometry as g


def random_T(rng):
    return g.make_T(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 5)


def test_convention_chains_by_inner_index():
    rng = np.random.default_rng(0)
    T_a_b, T_b_c = random_T(rng), random_T(rng)
    p_c = rng.normal(size=(10, 3))
    p_b = g.transform_points(T_b_c, p_c)
    p_a = g.transform_points(T_a_b, p_b)
    np.testing.assert_allclose(g.transform_points(T_a_b @ T_b_c, p_c), p_a, atol=1e-12)
    np.testing.assert_allclose(g.transform_points(g.inv(T_a_b), p_a), p_b, atol=1e-12)


def test_inverse_of_stack_and_relative():
    rng = np.random.default_rng(1)
    Ts = np.stack([random_T(rng) for _ in range(5)])
    np.testing.assert_allclose(g.inv(Ts) @ Ts, np.broadcast_to(np.eye(4), Ts.shape), atol=1e-12)
    rel = g.relative(Ts[:-1], Ts[1:])
    np.testing.assert_allclose(g.compose_relatives(rel, Ts[0]), Ts, atol=1e-10)


def test_exp_log_match_gtsam_rotation_first():
    rng = np.random.default_rng(2)
    for _ in range(5):
        xi = rng.normal(size=6) * [0.3, 0.3, 0.3, 2, 2, 2]
        T = g.exp_se3(xi)
        np.testing.assert_allclose(T, gtsam.Pose3.Expmap(xi).matrix(), atol=1e-10)
        np.testing.assert_allclose(g.log_se3(T), gtsam.Pose3.Logmap(gtsam.Pose3(T)), atol=1e-9)
        # right perturbation, as Pose3.retract
        X = random_T(rng)
        np.testing.assert_allclose(X @ g.exp_se3(xi), gtsam.Pose3(X).retract(xi).matrix(), atol=1e-9)


def test_quaternion_xyzw_roundtrip_and_angle():
    T = g.from_euler("z", 30, t=[1, 2, 3], degrees=True)
    q = g.to_quat_xyzw(T)
    np.testing.assert_allclose(q, [0, 0, np.sin(np.pi / 12), np.cos(np.pi / 12)], atol=1e-12)
    np.testing.assert_allclose(g.from_quat_xyzw(q, [1, 2, 3]), T, atol=1e-12)
    assert g.rotation_angle(T) == pytest.approx(np.deg2rad(30))
    assert g.translation_norm(T) == pytest.approx(np.sqrt(14))


def test_hat_is_cross_product_and_is_se3():
    w, x = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.2, -1.0])
    np.testing.assert_allclose(g.hat(w) @ x, np.cross(w, x))
    assert g.is_se3(g.from_euler("xyz", [0.1, 0.2, 0.3]))
    bad = np.eye(4)
    bad[0, 0] = 2
    assert not g.is_se3(bad)


def test_rotation_angle_precise_for_tiny_and_large_angles():
    for angle in [1e-9, 1e-6, 0.3, np.pi - 1e-6]:
        T = g.make_T(Rotation.from_rotvec(angle * np.array([1.0, -2.0, 2.0]) / 3.0).as_matrix())
        assert g.rotation_angle(T) == pytest.approx(angle, rel=1e-6)


def test_row_norms_equal_numpy_bit_for_bit():
    rng = np.random.default_rng(3)
    for shape, scale in [((10_000, 3), 40.0), ((5_000, 2), 1e-3), ((7, 3), 1e6), ((0, 3), 1.0)]:
        v = rng.normal(0.0, scale, shape)
        np.testing.assert_array_equal(g.row_norms(v), np.linalg.norm(v, axis=1))


def test_finite_rows_equal_numpy():
    v = np.random.default_rng(4).normal(0.0, 1.0, (1000, 3))
    v[[3, 10, 500], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    v[7] = 1e308  # finite, though its sum overflows
    np.testing.assert_array_equal(g.finite_rows(v), np.isfinite(v).all(axis=1))
    assert g.finite_rows(np.zeros((0, 3))).shape == (0,)
