"""RANSAC over point correspondences with 3-point minimal sets, then robust refinement.

Pipeline (all frames as in :func:`.kabsch.kabsch`: ``T_dst_src``, metres):

1. **Sampling**: batches of ``batch_size`` random 3-index samples. A sample is rejected
   before fitting if its indices repeat, if its source or destination triangle is
   degenerate (smallest triangle height, i.e. ``2 * area / longest side``, below
   ``threshold`` -- collinear or tiny samples leave the rotation about one axis
   undetermined), or if a pairwise distance differs between source and destination by
   more than ``2 * threshold`` (a rigid motion preserves distances, so such a sample
   holds an outlier).
2. **Hypotheses**: batched Kabsch on the surviving samples.
3. **Scoring**: MSAC cost ``sum min(r^2, threshold^2)`` of every hypothesis of the batch
   at once on a fixed random subset of ``score_samples`` correspondences (one
   (B,16) x (16,M) product of per-point moments, see ``irls._Moments``).
4. **Adaptive stopping**: with ``eps`` the best hypothesis' inlier ratio (on the subset),
   stop after ``log(1 - confidence) / log(1 - eps^3)`` draws (rejected samples count as
   draws: they are the failed ones), or at ``max_iterations`` draws.
5. **Local optimisation**: Kabsch on all inliers of the best hypothesis
   (``r < threshold``), repeated until the inlier set stops changing (at most ``lo_iterations`` times).
6. **Refinement**: :func:`.irls.irls` with ``refine_kernel`` on *all* correspondences,
   started from step 5, with the scale fixed to the robust sigma of the step-5 inliers
   (``median(r_inlier) / 1.5382``). Fixing the scale keeps the refinement valid above 50%
   outliers, where IRLS' own median scale would break down. ``refine_kernel=None`` skips
   this step (the result is then the least-squares fit of the inliers).

The returned ``inliers`` are ``residual < threshold`` at the final ``T``; the covariance
is the least-squares covariance of those inliers (see :mod:`.covariance`).
Deterministic for a given ``seed``.
"""

from __future__ import annotations

import math

import numpy as np

from .robust import (
    CHI3_MEDIAN,
    build_result,
    _Moments,
    _normalise_prior,
    _residual_norms,
    _run,
)
from .closed_form import check_correspondences, kabsch_batch
from .kernels import Kernel, get_kernel
from .result import RegistrationResult

__all__ = ["ransac", "required_iterations"]


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 3) -> float:
    """Draws needed to pick one all-inlier sample with probability ``confidence``."""
    p_good = float(inlier_ratio) ** sample_size
    if p_good <= 0.0:
        return math.inf
    if p_good >= 1.0:
        return 1.0
    return math.log(1.0 - confidence) / math.log1p(-p_good)


def _min_triangle_height(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest height ``2 * area / longest side`` of triangles (B,3) x3 -> (B,) (m)."""
    ab, ac, bc = b - a, c - a, c - b
    area2 = np.linalg.norm(np.cross(ab, ac), axis=1)
    longest = np.sqrt(np.maximum.reduce([(ab * ab).sum(1), (ac * ac).sum(1), (bc * bc).sum(1)]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(longest > 0, area2 / longest, 0.0)


def _is_collinear(points: np.ndarray) -> bool:
    """True if the points' scatter matrix has rank < 2 (collinear or coincident)."""
    c = points - np.einsum("ij->j", points) / len(points)
    ev = np.linalg.eigvalsh(np.einsum("ni,nj->ij", c, c))  # ascending
    return bool(ev[-1] <= 0 or ev[-2] <= 1e-12 * ev[-1])


def _check_not_collinear(points: np.ndarray, subset: np.ndarray, name: str) -> None:
    # A subset that is not collinear proves the whole set is not (cheap fast path).
    if _is_collinear(subset) and _is_collinear(points):
        raise ValueError(f"degenerate correspondences: all {name} points are collinear or coincident")


def ransac(
    src: np.ndarray,
    dst: np.ndarray,
    *,
    threshold: float,
    max_iterations: int = 1000,
    confidence: float = 0.999,
    refine_kernel: str | Kernel | None = "cauchy",
    seed: int | np.random.Generator | None = 0,
    batch_size: int = 64,
    score_samples: int = 4096,
    weights: np.ndarray | None = None,
    refine_max_iterations: int = 50,
    refine_tolerance: float = 1e-9,
    min_scale: float = 1e-4,
    lo_iterations: int = 3,
) -> RegistrationResult:
    """Robust ``T_dst_src`` from correspondences with many gross outliers.

    Parameters
    ----------
    src, dst:
        (N,3) putative correspondences (m), N >= 3.
    threshold:
        Inlier bound on the residual norm ``|R src + t - dst|`` (m), e.g. 3-5x the
        per-axis noise sigma.
    max_iterations:
        Cap on 3-point samples drawn.
    confidence:
        Probability of having drawn at least one all-inlier sample (adaptive stop).
    refine_kernel:
        Kernel for the final IRLS over all points (``None``: no IRLS).
    seed:
        Seed or ``numpy.random.Generator``; the same seed gives the same result.
    batch_size:
        Samples drawn and scored together.
    score_samples:
        Size of the random subset hypotheses are scored on (all points if N is smaller).
    weights:
        Optional (N,) prior weights passed to the refinement (and the covariance).
    refine_max_iterations, refine_tolerance, min_scale:
        Passed to :func:`.irls.irls` (``min_scale`` also floors the fixed scale).
    lo_iterations:
        Cap on the least-squares refits of the inlier set (local optimisation).

    Returns
    -------
    RegistrationResult
        ``iterations`` = samples drawn; ``info`` holds ``hypotheses`` (fitted and
        scored), ``required`` (adaptive draw count), ``ransac_inliers``,
        ``irls_iterations``. ``converged``: the confidence was reached (and the
        refinement converged).

    Raises
    ------
    ValueError
        Fewer than 3 points, bad parameters, all points collinear, or no non-degenerate,
        distance-consistent sample / fewer than 3 inliers found.
    """
    src, dst = check_correspondences(src, dst)
    n = len(src)
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0 (m), got {threshold}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if max_iterations < 1 or batch_size < 1 or score_samples < 3:
        raise ValueError("max_iterations, batch_size must be >= 1 and score_samples >= 3")
    kern = None if refine_kernel is None else get_kernel(refine_kernel)
    prior, active = _normalise_prior(weights, n)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    if n > score_samples:
        sub = np.sort(rng.choice(n, size=score_samples, replace=False))
        s_src, s_dst = src[sub], dst[sub]
    else:
        s_src, s_dst = src, dst
    _check_not_collinear(src, s_src, "source")
    _check_not_collinear(dst, s_dst, "destination")
    m = len(s_src)
    scorer = _Moments(s_src, s_dst)  # a batch of hypotheses scores as one (B,16)x(16,M) product
    thr2 = float(threshold) ** 2
    max_dist_diff = 2.0 * float(threshold)

    best_T: np.ndarray | None = None
    best_cost = math.inf
    best_count = 0
    drawn = 0
    hypotheses = 0
    required = math.inf
    while drawn < max_iterations and drawn < required:
        b = min(batch_size, max_iterations - drawn)
        idx = rng.integers(0, n, size=(b, 3))
        drawn += b
        i0, i1, i2 = idx[:, 0], idx[:, 1], idx[:, 2]
        ok = (i0 != i1) & (i0 != i2) & (i1 != i2)
        ps, qs = src[idx], dst[idx]  # (b,3,3)
        ok &= _min_triangle_height(ps[:, 0], ps[:, 1], ps[:, 2]) > threshold
        ok &= _min_triangle_height(qs[:, 0], qs[:, 1], qs[:, 2]) > threshold
        for a, c in ((0, 1), (0, 2), (1, 2)):
            d_s = np.linalg.norm(ps[:, a] - ps[:, c], axis=1)
            d_d = np.linalg.norm(qs[:, a] - qs[:, c], axis=1)
            ok &= np.abs(d_s - d_d) <= max_dist_diff
        if not np.any(ok):
            continue
        Ts = kabsch_batch(ps[ok], qs[ok])  # (v,4,4)
        hypotheses += len(Ts)
        r2 = scorer.squared_residuals_batch(scorer.to_centred(Ts))  # (v,m)
        cost = np.minimum(r2, thr2).sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost = float(cost[k])
            best_T = Ts[k]
            best_count = int(np.count_nonzero(r2[k] < thr2))
            required = required_iterations(best_count / m, confidence)

    if best_T is None:
        raise ValueError(
            f"degenerate correspondences: no non-collinear, distance-consistent 3-point sample "
            f"in {drawn} draws (threshold {threshold} m)"
        )

    # Local optimisation: least squares on the full inlier set until it settles.
    # (Prior weights, if any, weight the refits; zero-weight points are never inliers.)
    mom = _Moments(src, dst)

    def inliers_at(Tc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = mom.squared_residuals(Tc)
        inl = r2 < thr2
        return (inl if active is None else inl & active), r2

    Tc = mom.to_centred(best_T)
    inl, r2 = inliers_at(Tc)
    for _ in range(lo_iterations):
        if np.count_nonzero(inl) < 3:
            break
        Tc_new = mom.kabsch(inl * (1.0 if prior is None else prior))
        new_inl, new_r2 = inliers_at(Tc_new)
        if np.count_nonzero(new_inl) < np.count_nonzero(inl):
            break  # keep the larger consensus
        Tc, r2 = Tc_new, new_r2
        if np.array_equal(new_inl, inl):
            break
        inl = new_inl
    if np.count_nonzero(inl) < 3:
        raise ValueError(f"RANSAC found fewer than 3 inliers within {threshold} m")
    ransac_inliers = int(np.count_nonzero(inl))
    T = mom.from_centred(Tc)

    irls_iterations = 0
    irls_converged = True
    if kern is not None:
        scale = max(float(min_scale), float(np.sqrt(np.median(r2[inl]))) / CHI3_MEDIAN)
        T, r, w, _, irls_iterations, irls_converged = _run(
            src, dst, mom, kern, T, prior, active, scale, refine_max_iterations, refine_tolerance, min_scale
        )
    else:
        scale = float("nan")
        r = _residual_norms(src, dst, T)
        w = (r < threshold).astype(np.float64)
        if prior is not None:
            w *= prior

    return build_result(
        src, T, r, w, r < threshold, active=active, prior=prior, iterations=drawn,
        converged=bool(drawn >= required) and irls_converged, scale=scale,
        info={
            "hypotheses": hypotheses,
            "required": required,
            "ransac_inliers": ransac_inliers,
            "irls_iterations": irls_iterations,
            "kernel": None if kern is None else kern.name,
        },
    )
