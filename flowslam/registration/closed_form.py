"""Weighted Kabsch / Umeyama rigid alignment (no scale).

Finds ``T_dst_src = argmin sum_i w_i |R p_i + t - q_i|^2`` over proper rotations,
``p_i`` in the source frame, ``q_i`` in the destination frame, metres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["kabsch", "kabsch_batch", "check_correspondences", "squared_residuals"]

#: Second singular value of the cross-covariance, relative to the first, below which
#: the points are treated as collinear (rotation about the line undetermined).
DEGENERACY_RTOL = 1e-10


def check_correspondences(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert two (N,3) arrays of corresponding points to float64."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or dst.shape != src.shape:
        raise ValueError(f"src and dst must both be (N,3); got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"need at least 3 correspondences, got {len(src)}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ValueError("src/dst contain NaN or inf (filter invalid correspondences first)")
    return src, dst


def _rotation_from_cross_covariance(H: np.ndarray) -> np.ndarray:
    """Proper rotation(s) maximising ``trace(R H)``, ``H = sum w p_c q_c^T`` ((...,3,3)).

    ``H = U S V^T``  ->  ``R = V diag(1, 1, d) U^T`` with ``d = sign(det(V U^T))``,
    which handles the reflection case (coplanar points or noise flipping the sign).
    """
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    Ut = np.swapaxes(U, -1, -2)
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    V = V.copy()
    V[..., :, 2] *= d[..., None]
    return V @ Ut


def squared_residuals(src: np.ndarray, dst: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N,) squared residual norms ``|R src + t - dst|^2`` (m²) of ``T = T_dst_src``.

    Row by row of ``R`` on the transposed views: no BLAS call (see :func:`kabsch`).
    """
    R, t = T[:3, :3], T[:3, 3]
    s, d = src.T, dst.T
    out = np.empty((3, src.shape[0]))
    for i in range(3):  # the 3 output coordinates, each vectorised over all points
        row = out[i]
        np.multiply(s[0], R[i, 0], out=row)
        row += s[1] * R[i, 1]
        row += s[2] * R[i, 2]
        row += t[i]
        row -= d[i]
    out *= out
    return out.sum(axis=0)


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares rigid transform ``T_dst_src`` (4,4) with ``dst ~= R src + t``.

    With centroids ``c_s = sum w p / sum w``, ``c_d = sum w q / sum w`` and
    ``H = sum w (p - c_s)(q - c_d)^T = U S V^T``: ``R = V diag(1, 1, d) U^T`` with
    ``d = sign(det(V U^T))`` (never a reflection), ``t = c_d - R c_s``.

    The O(N) sums run as ``np.einsum`` over transposed, contiguous (3,N) copies rather
    than BLAS calls: as fast at this size, and immune to a multi-threaded BLAS stalling
    on a busy 2-core machine.

    Parameters
    ----------
    src, dst:
        (N,3) corresponding points (m), source and destination frames, N >= 3.
    weights:
        Optional (N,) non-negative weights (any scale); ``None`` means all ones.

    Raises
    ------
    ValueError
        Fewer than 3 points, bad shapes, non-finite points, negative/non-finite or
        all-zero weights, or degenerate geometry (the weighted points are collinear in
        src or dst, so the rotation about that line is undetermined).
    """
    src, dst = check_correspondences(src, dst)
    sT = np.ascontiguousarray(src.T)
    dT = np.ascontiguousarray(dst.T)
    if weights is None:
        wsum = float(len(src))
        cs = sT.sum(axis=1) / wsum
        cd = dT.sum(axis=1) / wsum
        ps = sT - cs[:, None]
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != len(src):
            raise ValueError(f"weights must be (N,) with N={len(src)}; got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
        wsum = float(w.sum())
        if wsum <= 0.0:
            raise ValueError("all weights are zero")
        cs = np.einsum("in,n->i", sT, w) / wsum
        cd = np.einsum("in,n->i", dT, w) / wsum
        ps = sT - cs[:, None]
        ps *= w
    dT -= cd[:, None]
    return rigid_from_moments(np.einsum("in,jn->ij", ps, dT), cs, cd)


def rigid_from_moments(H: np.ndarray, cs: np.ndarray, cd: np.ndarray) -> np.ndarray:
    """``T_dst_src`` from the centred cross-covariance ``H = sum w p_c q_c^T`` and the
    weighted centroids ``cs`` (source) and ``cd`` (target); ValueError if degenerate."""
    s = np.linalg.svd(H, compute_uv=False)
    if not np.all(np.isfinite(s)) or s[0] == 0.0 or s[1] <= DEGENERACY_RTOL * s[0]:
        raise ValueError("degenerate correspondences: the (weighted) points are collinear or coincident")
    R = _rotation_from_cross_covariance(H)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T


def kabsch_batch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Unweighted Kabsch for a batch of small point sets: (B,K,3), (B,K,3) -> (B,4,4).

    No degeneracy check (callers such as RANSAC screen samples beforehand).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    cs = src.mean(axis=1)
    cd = dst.mean(axis=1)
    H = np.einsum("bki,bkj->bij", src - cs[:, None], dst - cd[:, None])
    R = _rotation_from_cross_covariance(H)
    T = np.zeros((len(src), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = cd - np.einsum("bij,bj->bi", R, cs)
    T[:, 3, 3] = 1.0
    return T
