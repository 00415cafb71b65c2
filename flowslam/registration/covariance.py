"""6x6 pose covariances: of a registration from its residuals, and of a pose's inverse.

Covariance from the residuals (Gauss-Newton / Laplace)
------------------------------------------------------
Residual of correspondence i at ``T = (R, t)`` (``T_dst_src``):

    r_i = R p_i + t - q_i                      (3-vector, m)

Under the right perturbation ``T' = T Exp(xi)``, ``xi = [omega, v]`` (GTSAM Pose3 order),
``R' = R Exp(omega)`` and ``t' = t + R v + O(|xi|^2)``, so

    dr_i/domega = -R hat(p_i),      dr_i/dv = R,      J_i = [-R hat(p_i), R]  (3x6).

The information ``sum_i w_i J_i^T J_i`` does not depend on R (``R^T R = I``):

    [[ tr(S2) I - S2,  hat(S1) ],
     [ -hat(S1),       S0 I    ]],   S0 = sum w,  S1 = sum w p,  S2 = sum w p p^T,

so it costs three weighted moments of the source points. The covariance is
``sigma^2 (sum w J^T J)^-1`` with the weighted residual variance per axis

    sigma^2 = sum w_i |r_i|^2 / (3 sum w_i - 6)

(3 residual components per point, 6 estimated parameters; weights are first divided
by their maximum so that unit weights give the textbook unbiased estimator). With 0/1
weights this is exactly the least-squares covariance on the selected points and noise
``q_i ~ N(., sigma^2 I)``.

Covariance of the inverse
-------------------------
A covariance ``Sigma`` in the right-perturbation tangent of ``T``: ``T_true = T Exp(xi)``,
``xi ~ N(0, Sigma)``, ``xi = [omega, v]``. Then, exactly (``T Exp(xi) T^-1 = Exp(Ad_T xi)``)::

    T_true^-1 = Exp(-xi) T^-1 = T^-1 (T Exp(-xi) T^-1) = T^-1 Exp(-Ad_T xi)

so the perturbation of the inverse is ``eta = -Ad_T xi`` and
``Cov(eta) = Ad_T Sigma Ad_T^T`` (:func:`inverse_covariance`), with GTSAM's adjoint in
``[rot, trans]`` order ``Ad_T = [[R, 0], [hat(t) R, R]]`` (``R, t`` of ``T``;
``gtsam.Pose3.AdjointMap``). Checked against GTSAM in ``tests/test_registration.py``.
"""

from __future__ import annotations

import numpy as np

from flowslam.geometry import adjoint, hat

from .closed_form import squared_residuals

__all__ = [
    "covariance_from_residuals",
    "covariance_from_squared_residuals",
    "information_matrix",
    "inverse_covariance",
    "residual_variance",
]


def information_matrix(src: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``sum_i w_i J_i^T J_i`` (6x6, [omega, v] order, per unit residual variance)."""
    # einsum over a contiguous (3,N) copy, not BLAS (see flowslam.registration.closed_form).
    sT = np.ascontiguousarray(np.asarray(src, dtype=np.float64).T)
    if weights is None:
        S0 = float(sT.shape[1])
        S1 = sT.sum(axis=1)
        S2 = np.einsum("in,jn->ij", sT, sT)
    else:
        w = np.asarray(weights, dtype=np.float64)
        S0 = float(w.sum())
        S1 = np.einsum("in,n->i", sT, w)
        S2 = np.einsum("in,jn->ij", sT * w, sT)
    info = np.empty((6, 6))
    info[:3, :3] = np.trace(S2) * np.eye(3) - S2
    info[:3, 3:] = hat(S1)
    info[3:, :3] = -info[:3, 3:]
    info[3:, 3:] = S0 * np.eye(3)
    return info


def residual_variance(residual_sq: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Per-axis variance ``sum w |r|^2 / (3 sum w - 6)`` from squared residual norms (m²)."""
    r2 = np.asarray(residual_sq, dtype=np.float64)
    if weights is None:
        return float(r2.sum() / max(3.0 * len(r2) - 6.0, 1.0))
    w = np.asarray(weights, dtype=np.float64)
    return float(np.einsum("n,n->", w, r2) / max(3.0 * w.sum() - 6.0, 1.0))


def covariance_from_residuals(
    src: np.ndarray,
    dst: np.ndarray,
    T: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    sigma: float | None = None,
) -> np.ndarray:
    """Covariance (6x6, [omega, v], rad²/m²) of ``T = T_dst_src`` fitted to ``dst ~= T src``.

    Parameters
    ----------
    src, dst:
        (N,3) corresponding points (m) in the source and destination frames.
    T:
        (4,4) estimate ``T_dst_src``; the covariance lives in its right-perturbation
        tangent, ``T_true = T @ Exp(xi)``, ``xi ~ N(0, cov)``.
    weights:
        (N,) non-negative weights (e.g. 0/1 inlier mask times prior weights);
        ``None`` means all ones. Only their relative size matters.
    sigma:
        Known per-axis noise std (m); if ``None`` it is estimated from the residuals.

    Raises
    ------
    ValueError
        Fewer than 3 points with non-zero weight, bad shapes, or a singular
        information matrix (collinear points).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or dst.shape != src.shape:
        raise ValueError(f"src and dst must both be (N,3); got {src.shape} and {dst.shape}")
    r2 = squared_residuals(src, dst, np.asarray(T, dtype=np.float64))
    return covariance_from_squared_residuals(src, r2, weights, sigma=sigma)


def covariance_from_squared_residuals(
    src: np.ndarray,
    residual_sq: np.ndarray,
    weights: np.ndarray | None = None,
    *,
    sigma: float | None = None,
) -> np.ndarray:
    """As :func:`covariance_from_residuals`, given the (N,) squared residual norms (m²).

    The information matrix only needs the source points, so callers that already hold
    the residuals skip a transform.
    """
    src = np.asarray(src, dtype=np.float64)
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != len(src):
            raise ValueError(f"weights must be (N,) with N={len(src)}; got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
        wmax = float(w.max()) if w.size else 0.0
        if not wmax > 0:
            raise ValueError("all weights are zero")
        w = w / wmax
        if np.count_nonzero(w) < 3:
            raise ValueError("need at least 3 correspondences with non-zero weight")
    elif len(src) < 3:
        raise ValueError(f"need at least 3 correspondences, got {len(src)}")
    sigma2 = residual_variance(residual_sq, w) if sigma is None else float(sigma) ** 2
    info = information_matrix(src, w)
    s = np.linalg.svd(info, compute_uv=False)
    if not np.all(np.isfinite(s)) or s[-1] <= 1e-12 * s[0]:
        raise ValueError("singular information matrix: the points are collinear")
    cov = sigma2 * np.linalg.inv(info)
    return 0.5 * (cov + cov.T)


def inverse_covariance(T: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance of ``inv(T)`` from the covariance of ``T`` (both right-perturbation,
    ``[rot, trans]``): ``Ad_T Sigma Ad_T^T`` (derivation in the module doc)."""
    A = adjoint(T)
    C = A @ covariance @ A.T
    return 0.5 * (C + C.T)
