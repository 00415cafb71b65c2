"""Odometry fallbacks and motion-fault recoveries: their codes and their count for the run report.

A frame whose motion cannot be measured gets the constant-velocity prediction
(:mod:`flowslam.motion_model`) instead; :class:`flowslam.flow_odometry.FlowToPose`
records why under one of :data:`FALLBACK_CODES`, in its ``fallbacks`` counter and in the
frame's ``FrontendOutput.stats`` (``fallback``, ``fallback_code``), which
:func:`summarize_fallbacks` counts.

A frontend that checks its steps for motion faults (``ssf``, see
:mod:`flowslam.registration.recovery`) records ``stats["recovery"] = {"faults": [cue,
...], "outcome": ...}`` on every checked frame; the summary then also counts the
faulty steps by cue and by outcome, and ``recoveries``: the steps whose re-initialised
solution was kept.
"""

from __future__ import annotations

from collections import Counter

__all__ = ["FALLBACK_CODES", "RECOVERY_OUTCOMES", "summarize_fallbacks"]

#: Fallback codes and what they mean (keys of :attr:`flowslam.flow_odometry.FlowToPose.fallbacks`).
FALLBACK_CODES = {
    "few_points": "fewer usable static points than min_static_points",
    "ill_conditioned": "condition number of the scaled information above the threshold",
    "degenerate": "registration failed (collinear points, singular covariance)",
    "few_inliers": "too few pairs agree with the registered motion",
    "no_flow": "the frame has no flow (frontend-reported)",
}

#: What became of a faulty step (``stats["recovery"]["outcome"]``).
RECOVERY_OUTCOMES = {
    "recovered": "re-initialised globally; the new solution explains the scans better and was kept",
    "kept": "re-initialised globally; the first solution explained the scans as well and was kept",
    "confirmed": "first step checked: the global start agreed with its solution, which was kept without a retry",
    "no_start": "no global start could be found (too few points, low RANSAC fitness)",
    "off": "recovery switched off: detected and counted only",
}


def summarize_fallbacks(frontend_stats: list[dict]) -> dict:
    """Fallback counts for the run report from the per-frame ``FrontendOutput.stats``:
    ``{"frames": n, "fallbacks": k, "by_reason": {code: count}}``; when the frontend checks
    for motion faults also ``"recoveries": r`` and ``"motion_faults": {"checked": c,
    "detected": d, "by_cue": {cue: count}, "by_outcome": {outcome: count}}``."""
    codes = Counter(s.get("fallback_code", "unknown") for s in frontend_stats if s.get("fallback"))
    summary = {"frames": len(frontend_stats), "fallbacks": int(sum(codes.values())), "by_reason": dict(codes)}
    checks = [s["recovery"] for s in frontend_stats if isinstance(s.get("recovery"), dict)]
    if checks:
        faulty = [r for r in checks if r.get("faults")]
        outcomes = Counter(r.get("outcome") or "none" for r in faulty)
        summary["recoveries"] = outcomes.get("recovered", 0)
        summary["motion_faults"] = {
            "checked": len(checks), "detected": len(faulty),
            "by_cue": dict(Counter(c for r in faulty for c in r["faults"])), "by_outcome": dict(outcomes),
        }
    return summary
