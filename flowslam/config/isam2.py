"""Options of the ``isam2`` backend (``isam2:`` in the run config).

Radians and metres; ``_deg`` fields in degrees; kernel widths in whitened (unit-sigma)
residual units. Whether loops are searched for is ``loop_closure.enabled``, not a
backend option: the backend adds every loop it is given.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from flowslam.config.base import StrictModel


class Isam2Config(StrictModel):
    """GTSAM iSAM2 over one Pose3 per scan: relinearisation, robust kernels, priors."""

    relinearize_threshold_rad: float = Field(0.02, gt=0)
    """Relinearise a pose when a rotation component of its linear delta exceeds this (rad) ..."""
    relinearize_threshold_m: float = Field(1.0, gt=0)
    """... or a translation component exceeds this (m)."""
    relinearize_skip: int = Field(1, ge=1)
    """Check for relinearisation every this many updates."""
    factorization: Literal["cholesky", "qr"] = "cholesky"
    """Linear solver of iSAM2: Cholesky (fast, GTSAM's default) or QR (more stable)."""
    partial_relinearization_check: bool = True
    """GTSAM's ``enablePartialRelinearizationCheck``: check the Bayes tree from the root down,
    only into cliques that need relinearising, instead of every variable at each update.
    On by default: the full check made the update grow with the graph (KITTI-00 bench,
    4,541 poses, 18 loops: median update in the last 500 scans 0.69 ms full, 0.37 ms partial,
    as with no relinearisation at all; a 300-scan kiss-icp run with map factors: p95 update
    4.8 -> 1.0 ms) at no cost in accuracy: the final (refined) trajectories with loops
    differ by < 0.01 mm, ATE equal to 4 digits; iSAM2's online estimates differ by up to
    0.65 m after loops, less than either's own gap to the refined optimum (0.5-1.3 m);
    a-loam with map factors (no refinement): 2.3 mm apart, both 8.7 mm from the batch
    optimum. Kept over ``relinearize_skip: 10`` (as fast) because that skips the check in
    the empty updates of ``extra_iterations_after_loop``. Measurements: docs/soak.md."""
    huber_k: float = Field(1.345, gt=0)
    """Huber kernel width of the odometry factors."""
    cauchy_k: float = Field(3.0, gt=0)
    """Cauchy kernel width of the loop factors, in units of the loop's *combined* 1-sigma
    (see ``chain_aware_loop_kernel``)."""
    chain_aware_loop_kernel: bool = True
    """Widen each loop's Cauchy kernel by the odometry chain's own uncertainty between its
    two scans: k = cauchy_k * sqrt(1 + var_chain / var_loop) (the larger of the rotation and
    translation ratios; capped by ``max_loop_kernel_scale``). A true loop that disagrees by
    the drift the odometry covariances allow keeps its weight; a loop far outside that envelope is still cut down. Off: the
    kernel sees the loop's own covariance only, and true loops after long drift are ignored."""
    max_loop_kernel_scale: float = Field(5.0, ge=1.0)
    """Cap of that widening: a loop must still agree with the chain to within
    ``cauchy_k * max_loop_kernel_scale`` loop sigmas to keep a useful weight, so a false loop
    between far-apart scans (whose chain uncertainty is huge) stays cut down."""
    prior_rotation_sigma_deg: float = Field(1e-4, gt=0)
    """Prior on the first pose (at the identity): rotation 1-sigma per axis (deg) ..."""
    prior_translation_sigma_m: float = Field(1e-4, gt=0)
    """... and translation 1-sigma per axis (m)."""
    fallback_rotation_sigma_deg: float = Field(0.5, gt=0)
    """Odometry covariance used when the frontend gives none or one iSAM2 cannot use:
    rotation 1-sigma per axis (deg) ..."""
    fallback_translation_sigma_m: float = Field(0.2, gt=0)
    """... and translation 1-sigma per axis (m)."""
    extra_iterations_after_loop: int = Field(1, ge=0)
    """Empty iSAM2 updates after each loop factor (stop early once nothing relinearises)."""
    refine_iterations: int = Field(30, ge=0)
    """``trajectory()`` of a graph with loops: at most this many batch Levenberg-Marquardt
    iterations from the iSAM2 estimate (0 = return the iSAM2 estimate as it is)."""

