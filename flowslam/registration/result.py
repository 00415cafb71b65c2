"""The result type shared by every registration routine (:func:`kabsch`-based IRLS, RANSAC)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["RegistrationResult"]


@dataclass
class RegistrationResult:
    """Outcome of registering ``src`` (N,3) onto ``dst`` (N,3) correspondences.

    Attributes
    ----------
    T:
        (4,4) float64 ``T_dst_src`` ("T_target_source"): maps source points onto
        the target, ``dst ~= R @ src + t`` (metres).
    weights:
        (N,) final per-correspondence weights in [0, 1] (robust kernel weight times
        the max-normalised prior weight).
    inliers:
        (N,) bool, residual norm below the routine's inlier threshold.
    covariance:
        (6,6) covariance of ``T`` in GTSAM's tangent order ``[omega (rad), v (m)]``
        under the right perturbation ``T_true = T @ Exp(xi)``; units rad², rad·m, m².
    residuals:
        (N,) residual norms ``|R src_i + t - dst_i|`` (m) at the final ``T``.
    iterations:
        IRLS: iterations used. RANSAC: 3-point samples drawn (the refinement's IRLS
        iterations are in ``info["irls_iterations"]``).
    converged:
        True when the stopping criterion was met before the iteration cap.
    num_inliers:
        ``inliers.sum()``.
    rmse:
        Root-mean-square residual norm over the inliers (m); ``nan`` with no inliers.
    scale:
        Residual scale used at the end (per-axis noise sigma estimate, m); ``nan`` if
        not applicable.
    info:
        Free-form diagnostics (e.g. RANSAC hypothesis counts); not part of the contract.
    """

    T: np.ndarray
    weights: np.ndarray
    inliers: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    iterations: int
    converged: bool
    num_inliers: int
    rmse: float
    scale: float = float("nan")
    info: dict = field(default_factory=dict)

    @property
    def T_target_source(self) -> np.ndarray:
        """Alias of :attr:`T` spelled with the frame names."""
        return self.T
