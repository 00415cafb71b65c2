"""Tests of the registration core: Kabsch, kernels, IRLS, RANSAC and covariance
(of a registration and of a pose's inverse).

Frames: every routine returns ``T_dst_src`` (``dst ~= R src + t``), metres/radians.
Errors are measured as ``inv(T_true) @ T_est`` (translation norm, rotation angle).
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowslam.geometry import (
    adjoint,
    exp_se3,
    from_euler,
    hat,
    inv,
    log_se3,
    make_T,
    rotation_angle,
    transform_points,
)
from flowslam.registration import (
    RegistrationResult,
    covariance_from_residuals,
    get_kernel,
    inverse_covariance,
    irls,
    kabsch,
    ransac,
)
from flowslam.registration.covariance import information_matrix

KERNELS = ["huber", "cauchy", "geman_mcclure"]
N_SCENE = 60_000
NOISE = 0.01  # m, per axis, on inliers
OUTLIER_RATIO = 0.4
THRESHOLD = 0.05  # m, RANSAC inlier bound (5 sigma)
MAX_TRANS_ERR = 1e-3  # m
MAX_ROT_ERR = np.deg2rad(0.01)  # rad


def random_T(rng: np.random.Generator, angle_deg: float = 30.0, trans: float = 3.0) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    t = rng.normal(size=3)
    t *= trans / np.linalg.norm(t)
    return make_T(Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix(), t)


def pose_error(T_true: np.ndarray, T_est: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error rad) of ``inv(T_true) @ T_est``."""
    D = inv(T_true) @ T_est
    return float(np.linalg.norm(D[:3, 3])), float(rotation_angle(D))


def make_scene(
    n: int = N_SCENE,
    outlier_ratio: float = OUTLIER_RATIO,
    noise: float = NOISE,
    seed: int = 7,
    structured: bool = False,
):
    """A LiDAR-sized scene: 20 deg about a tilted axis, 3 m translation.

    Inliers: ``dst = T src + N(0, noise^2 I)``. Outliers: uniform random targets inside
    the bounding box of the inlier targets, or (``structured``) a second rigid motion
    1.5 m / 3 deg away (a large moving object).
    """
    rng = np.random.default_rng(seed)
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    t = np.array([2.0, -1.5, 2.0])
    T = make_T(Rotation.from_rotvec(np.deg2rad(20.0) * axis).as_matrix(), 3.0 * t / np.linalg.norm(t))
    src = rng.uniform([-30.0, -30.0, -2.0], [30.0, 30.0, 4.0], size=(n, 3))
    dst = transform_points(T, src) + rng.normal(0.0, noise, size=(n, 3))
    outlier = rng.random(n) < outlier_ratio
    if structured:
        T_other = T @ exp_se3([0.0, 0.0, np.deg2rad(3.0), 1.5, 0.3, 0.0])
        dst[outlier] = transform_points(T_other, src[outlier]) + rng.normal(0.0, noise, (outlier.sum(), 3))
    else:
        lo, hi = dst[~outlier].min(axis=0), dst[~outlier].max(axis=0)
        dst[outlier] = rng.uniform(lo, hi, size=(outlier.sum(), 3))
    return src, dst, T, outlier


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def assert_accurate(T_true, T_est, max_t=MAX_TRANS_ERR, max_r=MAX_ROT_ERR, what=""):
    et, er = pose_error(T_true, T_est)
    assert et < max_t and er < max_r, f"{what}: error {et * 1e3:.3f} mm, {np.rad2deg(er):.5f} deg"


def assert_outlier_labelling(result: RegistrationResult, outlier: np.ndarray, min_score: float = 0.99):
    predicted = ~result.inliers
    true_pos = np.count_nonzero(predicted & outlier)
    recall = true_pos / np.count_nonzero(outlier)
    precision = true_pos / max(np.count_nonzero(predicted), 1)
    assert recall > min_score and precision > min_score, f"outlier recall {recall:.4f}, precision {precision:.4f}"


# --------------------------------------------------------------------------- Kabsch


@pytest.mark.parametrize("offset", [0.0, 500.0])
def test_kabsch_exact_recovery(offset):
    rng = np.random.default_rng(1)
    for _ in range(5):
        T = random_T(rng, angle_deg=rng.uniform(1, 170), trans=rng.uniform(0.1, 10))
        src = rng.normal(size=(100, 3)) * 10.0 + offset
        dst = transform_points(T, src)
        T_est = kabsch(src, dst)
        assert np.abs(T_est - T).max() < 1e-9
        np.testing.assert_array_equal(T_est[3], [0, 0, 0, 1])


def test_kabsch_weighted_equals_duplicated_points():
    rng = np.random.default_rng(2)
    T = random_T(rng)
    src = rng.normal(size=(40, 3)) * 5.0
    dst = transform_points(T, src) + rng.normal(0, 0.05, size=(40, 3))
    counts = rng.integers(1, 5, size=40)
    T_w = kabsch(src, dst, counts.astype(float))
    T_dup = kabsch(np.repeat(src, counts, axis=0), np.repeat(dst, counts, axis=0))
    assert np.abs(T_w - T_dup).max() < 1e-12
    # Only relative weights matter; zero weights drop points.
    assert np.abs(kabsch(src, dst, 3.7 * counts) - T_w).max() < 1e-12
    w = np.ones(40)
    w[:10] = 0.0
    assert np.abs(kabsch(src, dst, w) - kabsch(src[10:], dst[10:])).max() < 1e-12


def test_kabsch_reflection_case():
    rng = np.random.default_rng(3)
    # (a) coplanar points: the SVD's third direction is arbitrary, the naive R may be a reflection.
    for _ in range(20):
        T = random_T(rng, angle_deg=rng.uniform(5, 175))
        src = np.c_[rng.normal(size=(30, 2)) * 4.0, np.zeros(30)]
        T_est = kabsch(src, transform_points(T, src))
        assert np.linalg.det(T_est[:3, :3]) == pytest.approx(1.0)
        assert np.abs(T_est - T).max() < 1e-9
    # (b) a mirrored cloud: the best *proper* rotation (scipy oracle), never the mirror.
    src = rng.normal(size=(50, 3)) * np.array([5.0, 3.0, 1.0])
    dst = src * np.array([1.0, 1.0, -1.0]) + np.array([1.0, 2.0, 3.0])
    T_est = kabsch(src, dst)
    R = T_est[:3, :3]
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    R_oracle, _ = Rotation.align_vectors(dst - dst.mean(0), src - src.mean(0))
    np.testing.assert_allclose(R, R_oracle.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(T_est[:3, 3], dst.mean(0) - R @ src.mean(0), atol=1e-9)


def test_kabsch_errors():
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(10, 3))
    with pytest.raises(ValueError, match="at least 3"):
        kabsch(pts[:2], pts[:2])
    with pytest.raises(ValueError, match="zero"):
        kabsch(pts, pts, np.zeros(10))
    with pytest.raises(ValueError):
        kabsch(pts, pts, -np.ones(10))
    with pytest.raises(ValueError):
        kabsch(pts, pts[:9])
    line = np.outer(np.linspace(-5, 5, 10), [1.0, 2.0, 0.5]) + [1.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="collinear"):
        kabsch(line, line + 1.0)
    with pytest.raises(ValueError, match="collinear"):  # only two points carry weight
        kabsch(pts, pts, np.r_[1.0, 1.0, np.zeros(8)])


# --------------------------------------------------------------------------- kernels


def test_kernel_registry_and_formulas():
    assert get_kernel("Huber").name == "huber"
    assert get_kernel("gm") is get_kernel("geman-mcclure") is get_kernel("geman_mcclure")
    assert get_kernel(None).name == get_kernel("none").name == "l2"
    assert get_kernel(get_kernel("cauchy")).name == "cauchy"
    with pytest.raises(ValueError, match="unknown robust kernel"):
        get_kernel("tukeyy")
    c = 0.1
    r = np.array([0.0, 0.05, 0.1, 0.2, 1.0])
    np.testing.assert_allclose(get_kernel("huber").weight(r, c), [1, 1, 1, 0.5, 0.1])
    np.testing.assert_allclose(get_kernel("cauchy").weight(r, c), 1 / (1 + (r / c) ** 2))
    np.testing.assert_allclose(get_kernel("gm").weight(r, c), 1 / (1 + (r / c) ** 2) ** 2)
    np.testing.assert_allclose(get_kernel("l2").weight(r, c), 1.0)
    # w(r) == rho'(r) / r (the documented rho and w agree), weights in [0,1], non-increasing.
    rr = np.linspace(0.01, 1.0, 200)
    h = 1e-6
    for name in ["l2", *KERNELS]:
        k = get_kernel(name)
        drho = (k.rho(rr + h, c) - k.rho(rr - h, c)) / (2 * h)
        np.testing.assert_allclose(k.weight(rr, c), drho / rr, rtol=1e-5, atol=1e-7, err_msg=name)
        np.testing.assert_allclose(k.weight_sq(rr**2, c), k.weight(rr, c), rtol=1e-12)
        w = k.weight(rr, c)
        assert np.all((w >= 0) & (w <= 1)) and np.all(np.diff(w) <= 1e-15)
    with pytest.raises(ValueError):
        get_kernel("cauchy").weight(r, 0.0)


@pytest.mark.parametrize("kernel", KERNELS)
def test_kernel_tuning_gives_95_percent_efficiency(kernel):
    """The documented default widths: 95% efficiency for 3-D Gaussian residuals."""
    from scipy import integrate, stats

    k = get_kernel(kernel)
    pdf = stats.chi(3).pdf
    h = 1e-6

    def w(r):
        return float(k.weight(np.array([r]), k.tuning)[0])

    def dw(r):
        return (w(r + h) - w(max(r - h, 0.0))) / (r + h - max(r - h, 0.0))

    opts = dict(limit=200, points=[k.tuning])
    A = integrate.quad(lambda r: (w(r) + r * dw(r) / 3) * pdf(r), 0, 30, **opts)[0]
    B = integrate.quad(lambda r: w(r) ** 2 * r * r / 3 * pdf(r), 0, 30, **opts)[0]
    assert A * A / B == pytest.approx(0.95, abs=2e-3)


# --------------------------------------------------------------------------- acceptance


def test_ransac_irls_from_scratch_acceptance(scene):
    """40% gross outliers, 1 cm noise, 60k pairs: < 1 mm and < 0.01 deg, no init."""
    src, dst, T, outlier = scene
    res = ransac(src, dst, threshold=THRESHOLD, seed=0)
    assert isinstance(res, RegistrationResult)
    assert_accurate(T, res.T, what="ransac+cauchy")
    assert res.converged
    assert_outlier_labelling(res, outlier)
    assert res.num_inliers == np.count_nonzero(res.inliers)
    assert res.rmse == pytest.approx(NOISE * np.sqrt(3), rel=0.1)
    assert res.T.dtype == np.float64 and res.T.shape == (4, 4)
    for arr in (res.weights, res.inliers, res.residuals):
        assert arr.shape == (N_SCENE,)
    assert np.all((res.weights >= 0) & (res.weights <= 1))
    assert res.covariance.shape == (6, 6)


@pytest.mark.parametrize("kernel", KERNELS)
def test_ransac_then_irls_each_kernel(scene, kernel):
    src, dst, T, outlier = scene
    res = ransac(src, dst, threshold=THRESHOLD, refine_kernel=kernel, seed=1)
    assert_accurate(T, res.T, what=f"ransac+{kernel}")
    assert_outlier_labelling(res, outlier)


@pytest.mark.parametrize("kernel", KERNELS)
def test_irls_alone_each_kernel(scene, kernel):
    """IRLS without RANSAC, from the least-squares start, identity and near truth.

    With *uniform* outliers all three kernels reach the target even from identity:
    the outliers' pulls nearly cancel and the automatic scale starts wide (the median
    residual) and shrinks as the fit improves. Structured outliers are another matter
    (test_structured_outliers_bias_huber).
    """
    src, dst, T, outlier = scene
    near = T @ exp_se3([0.02, -0.02, 0.01, 0.2, 0.1, -0.2])  # ~1.7 deg, 30 cm off
    for name, init in [("least squares", None), ("identity", np.eye(4)), ("near truth", near)]:
        res = irls(src, dst, kernel=kernel, init=init)
        assert res.converged, f"{kernel} from {name}"
        assert_accurate(T, res.T, what=f"irls {kernel} from {name}")
        assert_outlier_labelling(res, outlier)
    # The automatic scale over-estimates sigma by ~1.5x at 40% outliers (documented).
    assert NOISE < res.scale < 2.0 * NOISE


def test_irls_l2_is_biased_by_outliers(scene):
    """Sanity: without a robust kernel the same data are off by > 1 cm."""
    src, dst, T, _ = scene
    et, _ = pose_error(T, irls(src, dst, kernel="l2").T)
    assert et > 0.01


def test_structured_outliers_bias_huber():
    """A 40% second rigid motion 1.5 m away: Huber's non-redescending influence biases it
    by centimetres; Geman-McClure (and Cauchy, less well) reject it, from RANSAC.
    """
    src, dst, T, outlier = make_scene(structured=True, seed=11)
    ransac_T = ransac(src, dst, threshold=THRESHOLD, refine_kernel=None).T
    assert_accurate(T, ransac_T, what="ransac LO only")
    et_huber, _ = pose_error(T, irls(src, dst, kernel="huber", init=ransac_T, max_iterations=200).T)
    assert et_huber > 5e-3
    assert_accurate(T, irls(src, dst, kernel="geman_mcclure", init=ransac_T).T, what="gm")
    assert_accurate(T, irls(src, dst, kernel="cauchy", init=ransac_T).T, max_t=2e-3, what="cauchy")
    res = ransac(src, dst, threshold=THRESHOLD, refine_kernel="geman_mcclure")
    assert_accurate(T, res.T, what="ransac+gm")
    assert_outlier_labelling(res, outlier)


def test_ransac_beyond_50_percent_outliers():
    """At 65% uniform outliers IRLS' median scale breaks down; RANSAC+IRLS does not."""
    src, dst, T, outlier = make_scene(n=20_000, outlier_ratio=0.65, seed=5)
    res = ransac(src, dst, threshold=THRESHOLD, seed=3)
    assert_accurate(T, res.T, what="ransac 65%")
    assert_outlier_labelling(res, outlier)
    et, _ = pose_error(T, irls(src, dst, kernel="cauchy").T)
    assert et > 0.01  # documented limitation of the automatic scale


def test_irls_noise_free_exact():
    rng = np.random.default_rng(6)
    T = random_T(rng)
    src = rng.uniform(-20, 20, size=(5000, 3))
    dst = transform_points(T, src)
    for kernel in ["l2", *KERNELS]:
        res = irls(src, dst, kernel=kernel)
        assert np.abs(res.T - T).max() < 1e-9, kernel
        assert res.converged and res.num_inliers == 5000
    # Gross outliers + exact inliers: the redescending kernels stay exact (Huber does not).
    outlier = rng.random(5000) < 0.3
    dst[outlier] = rng.uniform(-20, 20, size=(outlier.sum(), 3))
    res = irls(src, dst, kernel="geman_mcclure")
    assert np.abs(res.T - T).max() < 1e-9
    np.testing.assert_array_equal(res.inliers, ~outlier)


def test_irls_prior_weights_and_fixed_scale(scene):
    src, dst, T, outlier = scene
    # Prior weights that zero the outliers: plain L2 IRLS equals Kabsch on the inliers.
    prior = (~outlier).astype(float) * 0.5
    res = irls(src, dst, kernel="l2", weights=prior)
    assert np.abs(res.T - kabsch(src[~outlier], dst[~outlier])).max() < 1e-12
    assert not np.any(res.inliers[outlier])
    assert np.all(res.weights[outlier] == 0) and np.all(res.weights <= 1)
    # A fixed, correct scale works from the least-squares start too.
    res = irls(src, dst, kernel="cauchy", scale=NOISE)
    assert res.scale == NOISE
    assert_accurate(T, res.T, what="fixed scale")
    # With the true sigma the 4.03-sigma cut (not 3 sigma) keeps 99.9% of the inliers.
    assert_outlier_labelling(res, outlier, min_score=0.995)
    with pytest.raises(ValueError):
        irls(src, dst, scale=-1.0)
    with pytest.raises(ValueError):
        irls(src, dst, weights=np.zeros(len(src)))
    with pytest.raises(ValueError):
        irls(src, dst, kernel="nope")


# --------------------------------------------------------------------------- RANSAC


def test_ransac_deterministic_with_seed(scene):
    src, dst, T, _ = scene
    a = ransac(src[:20000], dst[:20000], threshold=THRESHOLD, seed=123)
    b = ransac(src[:20000], dst[:20000], threshold=THRESHOLD, seed=123)
    np.testing.assert_array_equal(a.T, b.T)
    np.testing.assert_array_equal(a.inliers, b.inliers)
    assert a.iterations == b.iterations and a.info == b.info
    c = ransac(src[:20000], dst[:20000], threshold=THRESHOLD, seed=np.random.default_rng(123))
    np.testing.assert_array_equal(a.T, c.T)
    # The adaptive count: ~28 draws suffice at a 60% inlier ratio, so one batch of 64.
    assert a.iterations == 64 and a.info["required"] < 64
    # Capped below the required count: still a usable estimate, but not "converged".
    capped = ransac(src[:20000], dst[:20000], threshold=THRESHOLD, seed=123, max_iterations=10, batch_size=5)
    assert capped.iterations == 10 and not capped.converged


def test_ransac_degenerate_inputs():
    rng = np.random.default_rng(8)
    pts = rng.normal(size=(10, 3))
    with pytest.raises(ValueError, match="at least 3"):
        ransac(pts[:2], pts[:2], threshold=0.1)
    line = np.outer(rng.uniform(-10, 10, 500), [1.0, -2.0, 0.5])
    with pytest.raises(ValueError, match="collinear"):
        ransac(line, line + [1.0, 2.0, 3.0], threshold=0.05)
    with pytest.raises(ValueError, match="collinear"):
        irls(line, line + [1.0, 2.0, 3.0])
    # Nearly collinear (jitter below the threshold): every sample is rejected.
    jitter = line + rng.normal(0, 1e-4, size=line.shape)
    with pytest.raises(ValueError, match="no non-collinear"):
        ransac(jitter, jitter, threshold=0.05, max_iterations=200)
    with pytest.raises(ValueError):
        ransac(pts, pts, threshold=0.0)


# --------------------------------------------------------------------------- covariance


def _residuals(src, dst, T):
    return (transform_points(T, src) - dst).ravel()


def test_covariance_jacobian_matches_finite_differences():
    """d r / d xi of r_i = R p_i + t - q_i at T Exp(xi), xi = [omega, v]."""
    rng = np.random.default_rng(9)
    T = random_T(rng, angle_deg=40.0)
    src = rng.normal(size=(20, 3)) * 5.0 + [10.0, -3.0, 2.0]
    dst = transform_points(T, src) + rng.normal(0, 0.1, size=src.shape)
    h = 1e-6
    J_num = np.empty((3 * len(src), 6))
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        J_num[:, k] = (_residuals(src, dst, T @ exp_se3(e)) - _residuals(src, dst, T @ exp_se3(-e))) / (2 * h)
    R = T[:3, :3]
    J = np.concatenate([np.hstack([-R @ hat(p), R]) for p in src])
    np.testing.assert_allclose(J, J_num, atol=1e-7)
    w = rng.uniform(0.2, 1.0, size=len(src))
    W = np.repeat(w / w.max(), 3)
    info = information_matrix(src, w / w.max())
    np.testing.assert_allclose(info, J_num.T @ (W[:, None] * J_num), rtol=1e-6, atol=1e-6)
    # sigma^2 = sum w |r|^2 / (3 sum w - 6) and cov = sigma^2 info^-1.
    r2 = ((transform_points(T, src) - dst) ** 2).sum(1)
    wn = w / w.max()
    sigma2 = (wn @ r2) / (3 * wn.sum() - 6)
    np.testing.assert_allclose(covariance_from_residuals(src, dst, T, w), sigma2 * np.linalg.inv(info), rtol=1e-9)


def test_covariance_monte_carlo():
    """Empirical covariance of Kabsch estimates (log(T_true^-1 T_est)) vs the prediction."""
    rng = np.random.default_rng(10)
    T = random_T(rng, angle_deg=25.0, trans=3.0)
    # An off-centre, anisotropic cloud, so rotation and translation are correlated.
    src = rng.normal(size=(200, 3)) * [6.0, 3.0, 1.0] + [8.0, 2.0, 1.0]
    clean = transform_points(T, src)
    sigma = 0.02
    trials = 2000
    xis = np.empty((trials, 6))
    predicted = []
    for k in range(trials):
        dst = clean + rng.normal(0, sigma, size=clean.shape)
        T_est = kabsch(src, dst)
        xis[k] = log_se3(inv(T) @ T_est)
        if k < 50:
            predicted.append(covariance_from_residuals(src, dst, T_est))
    cov_pred = np.mean(predicted, axis=0)
    cov_emp = np.cov(xis.T)
    ratio = np.diag(cov_emp) / np.diag(cov_pred)
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    # Off-diagonal structure too: the whitened errors have identity covariance.
    L = np.linalg.cholesky(np.linalg.inv(cov_pred))
    white = np.cov((xis @ L).T)
    np.testing.assert_allclose(white, np.eye(6), atol=0.2)
    assert abs(np.corrcoef(xis.T)[1, 5]) > 0.3  # the test would notice a wrong coupling
    # With the known sigma the prediction is exact up to sampling error.
    cov_known = covariance_from_residuals(src, clean, T, sigma=sigma)
    np.testing.assert_allclose(np.diag(cov_emp) / np.diag(cov_known), 1.0, atol=0.2)


def test_covariance_tangent_order_matches_gtsam():
    rng = np.random.default_rng(12)
    T = random_T(rng, angle_deg=50.0)
    pose = gtsam.Pose3(T)
    xi = np.array([1e-3, -2e-3, 3e-3, 0.01, -0.02, 0.03])  # rotation first
    np.testing.assert_allclose(pose.retract(xi).matrix(), T @ exp_se3(xi), atol=1e-12)
    np.testing.assert_allclose(pose.localCoordinates(gtsam.Pose3(T @ exp_se3(xi))), xi, atol=1e-12)
    # GTSAM's own Jacobian of transformFrom is our J_i = [-R hat(p), R].
    p = np.array([1.0, -2.0, 0.5])
    H_pose = np.zeros((3, 6), order="F")
    H_point = np.zeros((3, 3), order="F")
    pose.transformFrom(p, H_pose, H_point)
    np.testing.assert_allclose(H_pose, np.hstack([-T[:3, :3] @ hat(p), T[:3, :3]]), atol=1e-12)


def test_covariance_equals_gtsam_marginal():
    """A GTSAM graph of point factors (GTSAM's Jacobians) gives the same 6x6 marginal."""
    rng = np.random.default_rng(13)
    T = random_T(rng, angle_deg=30.0)
    src = rng.normal(size=(60, 3)) * [5.0, 2.0, 1.0] + [4.0, 1.0, 0.0]
    sigma = 0.03
    dst = transform_points(T, src) + rng.normal(0, sigma, size=src.shape)
    T_est = kabsch(src, dst)
    key = gtsam.symbol("x", 0)
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)

    def make_error(p, q):
        def error(this, values, H):
            Hp = np.zeros((3, 6), order="F")
            y = values.atPose3(this.keys()[0]).transformFrom(p, Hp, np.zeros((3, 3), order="F"))
            if H is not None:
                H[0] = Hp
            return y - q

        return error

    for p, q in zip(src, dst):
        graph.add(gtsam.CustomFactor(noise, [key], make_error(p, q)))
    values = gtsam.Values()
    values.insert(key, gtsam.Pose3(T_est))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    np.testing.assert_allclose(result.atPose3(key).matrix(), T_est, atol=1e-9)
    cov_gtsam = gtsam.Marginals(graph, result).marginalCovariance(key)
    np.testing.assert_allclose(covariance_from_residuals(src, dst, T_est, sigma=sigma), cov_gtsam, rtol=1e-6)


def test_inverse_covariance_against_gtsam_sampling():
    """Sample T_i = T Exp(xi_i), xi ~ N(0, Sigma); the right-tangent deviations of the
    inverses, Log(inv(T^-1) T_i^-1) = Log(T T_i^-1), have covariance Ad_T Sigma Ad_T^T."""
    rng = np.random.default_rng(6)
    T = gtsam.Pose3(from_euler("zyx", [25.0, 8.0, -4.0], t=[3.0, -1.0, 0.4], degrees=True))
    A = rng.normal(size=(6, 6))
    Sigma = A @ A.T * 1e-3 + np.diag([1e-4] * 3 + [1e-2] * 3)
    xi = rng.multivariate_normal(np.zeros(6), Sigma, size=20000)
    T_inv = T.inverse()
    eta = np.array([gtsam.Pose3.Logmap(T_inv.between(T.compose(gtsam.Pose3.Expmap(x)).inverse())) for x in xi])
    empirical = np.cov(eta.T)
    predicted = inverse_covariance(T.matrix(), Sigma)
    # the map is exactly linear (eta = -Ad_T xi), so only the sampling error remains
    np.testing.assert_allclose(eta, -xi @ adjoint(T.matrix()).T, atol=1e-9)
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.max(np.abs(empirical - predicted) / scale) < 0.05


def test_irls_covariance_is_inlier_least_squares(scene):
    src, dst, T, outlier = scene
    res = ransac(src, dst, threshold=THRESHOLD, seed=0)
    cov_true_inliers = covariance_from_residuals(src[~outlier], dst[~outlier], res.T)
    np.testing.assert_allclose(np.diag(res.covariance), np.diag(cov_true_inliers), rtol=0.05)
    # Predicted std is ~1e-4 m: the sub-millimetre acceptance bound is ~10 sigma wide.
    assert np.sqrt(res.covariance[3:, 3:].diagonal()).max() < 2e-4
    np.testing.assert_allclose(res.covariance, res.covariance.T)
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)
