"""Robust point-set registration: weighted Kabsch, IRLS, RANSAC, covariance, degeneracy checks.

All routines estimate ``T_dst_src`` (4x4, maps source points onto the target,
``dst ~= R src + t``, metres) and report covariances in GTSAM's Pose3 tangent order
``[omega, v]`` under the right perturbation (see :mod:`flowslam.geometry`).
"""

from .covariance import covariance_from_residuals, inverse_covariance
from .robust import irls
from .closed_form import kabsch
from .kernels import Kernel, get_kernel
from .consensus import ransac
from .result import RegistrationResult
from .degeneracy import correspondence_condition, geometry_condition

__all__ = [
    "kabsch",
    "irls",
    "ransac",
    "RegistrationResult",
    "covariance_from_residuals",
    "inverse_covariance",
    "correspondence_condition",
    "geometry_condition",
    "get_kernel",
    "Kernel",
]
