"""Degeneracy checks: is a registration problem well conditioned before solving it?

Each check returns the condition number of a scaled 6x6 information matrix (``inf``
when singular); a caller compares it with a threshold. Both informations are taken
about the centroid of the points, with rotations scaled by ``L`` = the RMS distance of
the points from that centroid, so a rotation ``omega`` counts as the displacement
``L omega`` it causes and both blocks are in metres:

- :func:`correspondence_condition`: the point-to-point information of point pairs
  (singular only for (nearly) collinear points);
- :func:`geometry_condition`: the point-to-plane information ``sum a a^T``,
  ``a = [(c x n)/L, n]``, of planar surfels (voxels of ``voxel_size``, default 2 m,
  normal ``n`` by PCA, weight = planarity, one vote per voxel). This is what the
  scene's geometry can tell a geometry-based estimator (e.g. scene flow): in a corridor
  no surface faces along the corridor, so the along-axis motion is unobservable
  (aperture problem) even though point pairs themselves look well conditioned. Real
  scans score 7-20 (AV2, KITTI; 3k to 30k points), a two-wall corridor with floor
  > 600. Scenes with fewer than 6 planar surfels count as degenerate (``inf``;
  unstructured random points).
"""

from __future__ import annotations

import numpy as np

from flowslam.mapping import voxel_ids

__all__ = ["correspondence_condition", "geometry_condition"]


def _scaled_condition(H: np.ndarray) -> float:
    """Condition number of a symmetric PSD 6x6 matrix (inf when singular)."""
    e = np.linalg.eigvalsh(H)
    if not np.all(np.isfinite(e)) or e[-1] <= 0:
        return float("inf")
    return float(e[-1] / e[0]) if e[0] > 1e-15 * e[-1] else float("inf")


def correspondence_condition(src: np.ndarray) -> float:
    """Condition number of the point-to-point information of pairs with sources ``src``
    (N,3), about their centroid, rotation scaled by the RMS radius ``L`` (module doc).

    Per point the (centred) information is ``[[|p|^2 I - p p^T, .], [., I]] / L^2``;
    about the centroid the cross block vanishes.
    """
    c = np.ascontiguousarray(src.T)  # (3,N): einsum over contiguous rows, no BLAS
    c -= c.mean(axis=1, keepdims=True)
    S2 = np.einsum("in,jn->ij", c, c) / c.shape[1]
    L2 = float(np.trace(S2))
    if not L2 > 0:
        return float("inf")
    H = np.zeros((6, 6))
    H[:3, :3] = (L2 * np.eye(3) - S2) / L2
    H[3:, 3:] = np.eye(3)
    return _scaled_condition(H)


def geometry_condition(points: np.ndarray, voxel_size: float = 2.0, min_voxel_points: int = 5) -> float:
    """Condition number of the point-to-plane information of the scene's surfels.

    Points (N,3, m) are grouped in ``voxel_size`` voxels; each voxel with at least
    ``min_voxel_points`` points gives a surfel: centroid ``m`` (relative to the
    points' centroid), normal ``n`` (smallest principal axis), planarity
    ``(l2 - l3) / l1`` (eigenvalues descending; 0 for lines and scatter, 1 for a
    plane). ``H = sum_v planarity_v a_v a_v^T / sum planarity``, ``a = [(m x n)/L, n]``,
    ``L`` the RMS radius of the points. ``inf`` if fewer than 6 surfels.
    """
    c0 = points.mean(axis=0)
    pc = points - c0
    L = float(np.sqrt(np.einsum("ni,ni->", pc, pc) / len(pc)))
    if not L > 0:
        return float("inf")
    inverse, counts = voxel_ids(pc, voxel_size)
    V = len(counts)
    S1 = np.stack([np.bincount(inverse, pc[:, i], V) for i in range(3)], axis=1)
    S2 = np.empty((V, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            S2[:, i, j] = S2[:, j, i] = np.bincount(inverse, pc[:, i] * pc[:, j], V)
    ok = counts >= min_voxel_points
    if np.count_nonzero(ok) < 6:
        return float("inf")
    n_v = counts[ok].astype(np.float64)
    m = S1[ok] / n_v[:, None]
    C = S2[ok] / n_v[:, None, None] - np.einsum("vi,vj->vij", m, m)
    w, vec = np.linalg.eigh(C)  # ascending
    normal = vec[:, :, 0]
    planarity = (w[:, 1] - w[:, 0]) / np.maximum(w[:, 2], 1e-12)
    wsum = float(planarity.sum())
    if not wsum > 0:
        return float("inf")
    a = np.hstack([np.cross(m, normal) / L, normal])
    H = np.einsum("v,vi,vj->ij", planarity, a, a) / wsum
    return _scaled_condition(H)
