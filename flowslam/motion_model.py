"""Constant-velocity motion model: the prediction an odometry falls back to.

When a scan pair cannot be registered, the odometry measurement is the
**constant-velocity prediction**: the last registered ``T_prev_curr`` (scan k into frame
k-1, see :mod:`flowslam.interfaces`), its twist scaled by the ratio of scan intervals
when both are known (constant velocity in time, not per scan), with an inflated
covariance

    fallback_inflation * C_last + m * diag(fallback_std^2)

``C_last`` the covariance of the last registered measurement and ``m`` the number of
consecutive predictions (a random walk on the velocity). Without any previous
measurement the prediction is the identity (standing still) with
``diag(no_prior_std^2)``. Covariances are 6x6 in the right-perturbation tangent of
``T_prev_curr``, ``[omega rad, v m]``; the options are fields of
:class:`flowslam.config.odometry.FlowOdometryConfig`.
"""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np

from flowslam import geometry
from flowslam.config.odometry import FlowOdometryConfig

log = logging.getLogger(__name__)

__all__ = ["ConstantVelocityPredictor"]


class ConstantVelocityPredictor:
    """Holds the last registered measurement and predicts the next one from it.

    ``predict(dt)`` returns ``T_prev_curr`` of the last registration, its twist scaled
    by ``dt / dt_last`` when both intervals are known (constant velocity in time, not
    per scan), and the covariance of a prediction ``misses`` steps after it (module doc).
    """

    def __init__(self, config: FlowOdometryConfig):
        self.config = config
        self.T_prev_curr: np.ndarray | None = None
        self.covariance: np.ndarray | None = None
        self.dt: float | None = None
        self.misses = 0
        """Consecutive predictions since the last registered measurement."""
        self.fallbacks: Counter[str] = Counter()
        """Fallbacks so far, by code (see :data:`flowslam.fallbacks.FALLBACK_CODES`)."""

    def update(self, T_prev_curr: np.ndarray, covariance: np.ndarray, dt: float | None) -> None:
        """Record a registered (non-fallback) measurement."""
        self.T_prev_curr = np.array(T_prev_curr, dtype=np.float64)
        self.covariance = np.array(covariance, dtype=np.float64)
        self.dt = dt if dt is not None and dt > 0 else None
        self.misses = 0

    def snapshot(self) -> dict:
        """The predictor's state (a copy), for :meth:`restore`: a caller that registers a
        pair twice (motion-fault recovery) keeps the state of the solution it keeps."""
        return dict(T_prev_curr=self.T_prev_curr, covariance=self.covariance, dt=self.dt, misses=self.misses,
                    fallbacks=Counter(self.fallbacks))

    def restore(self, snapshot: dict) -> None:
        """Go back to a state of :meth:`snapshot` (arrays are replaced on update, never
        changed in place, so sharing them is safe)."""
        self.T_prev_curr, self.covariance, self.dt = snapshot["T_prev_curr"], snapshot["covariance"], snapshot["dt"]
        self.misses = snapshot["misses"]
        self.fallbacks = Counter(snapshot["fallbacks"])

    def predict(self, dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(T_prev_curr, covariance) of the next scan pair; counts one more miss."""
        cfg = self.config
        self.misses += 1
        if self.T_prev_curr is None:
            return np.eye(4), geometry.pose_covariance(
                np.deg2rad(cfg.no_prior_rotation_std_deg), cfg.no_prior_translation_std_m)
        T = self.T_prev_curr
        if dt is not None and dt > 0 and self.dt is not None:
            T = geometry.exp_se3(geometry.log_se3(T) * (dt / self.dt))
        model = geometry.pose_covariance(np.deg2rad(cfg.fallback_rotation_std_deg), cfg.fallback_translation_std_m)
        cov = cfg.fallback_inflation * self.covariance + self.misses * model
        return T.copy(), cov

    def fall_back(self, code: str, reason: str, dt: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
        """The prediction for a pair that could not be registered, counted under ``code``,
        and the frame stats that say so (what ``summarize_fallbacks`` counts)."""
        T, cov = self.predict(dt)
        self.fallbacks[code] += 1
        log.info("fallback to constant velocity (%s): %s", code, reason)
        stats = dict(fallback=True, reason=reason, fallback_code=code, method="constant-velocity",
                     consecutive_fallbacks=self.misses)
        return T, cov, stats
