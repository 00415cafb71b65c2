"""Odometry fallbacks: their codes and their count for the run report.

A frame whose motion cannot be measured gets the constant-velocity prediction
(:mod:`flowslam.motion_model`) instead; :class:`flowslam.flow_odometry.FlowToPose`
records why under one of :data:`FALLBACK_CODES`, in its ``fallbacks`` counter and in the
frame's ``FrontendOutput.stats`` (``fallback``, ``fallback_code``), which
:func:`summarize_fallbacks` counts.
"""

from __future__ import annotations

from collections import Counter

__all__ = ["FALLBACK_CODES", "summarize_fallbacks"]

#: Fallback codes and what they mean (keys of :attr:`flowslam.flow_odometry.FlowToPose.fallbacks`).
FALLBACK_CODES = {
    "few_points": "fewer usable static points than min_static_points",
    "ill_conditioned": "condition number of the scaled information above the threshold",
    "degenerate": "registration failed (collinear points, singular covariance)",
    "few_inliers": "too few pairs agree with the registered motion",
    "no_flow": "the frame has no flow (frontend-reported)",
}


def summarize_fallbacks(frontend_stats: list[dict]) -> dict:
    """Fallback counts for the run report from the per-frame ``FrontendOutput.stats``:
    ``{"frames": n, "fallbacks": k, "by_reason": {code: count}}``."""
    codes = Counter(s.get("fallback_code", "unknown") for s in frontend_stats if s.get("fallback"))
    return {"frames": len(frontend_stats), "fallbacks": int(sum(codes.values())), "by_reason": dict(codes)}
