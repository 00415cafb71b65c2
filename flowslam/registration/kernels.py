"""Robust kernels as IRLS weight functions of the residual norm.

Every kernel is a function of the residual *norm* ``r = |R p + t - q| >= 0`` (m) and a
width ``c > 0`` (m). IRLS minimises ``sum rho(r_i; c)`` by solving weighted least squares
with ``w(r) = rho'(r) / r``:

=================  ====================================  =============================  ======
kernel             rho(r; c)                             w(r; c)                        tuning
=================  ====================================  =============================  ======
``l2`` / ``none``  r^2 / 2                               1                              --
``huber``          r^2/2 (r <= c);  c (r - c/2) (r > c)  1 (r <= c);  c / r (r > c)     1.628
``cauchy``         c^2/2 log(1 + (r/c)^2)                1 / (1 + (r/c)^2)              2.666
``geman_mcclure``  (r^2/2) / (1 + (r/c)^2)               1 / (1 + (r/c)^2)^2            4.337
=================  ====================================  =============================  ======

Huber is convex in the residual (forgiving of a poor start), but its influence
``r w(r)`` never falls below ``c``, so gross outliers keep pulling: structured outliers
(a moving object) bias it by centimetres. Cauchy and Geman-McClure are redescending (an
outlier at ``r >> c`` gets weight ~ ``(c/r)^2`` resp. ``(c/r)^4``; their pull vanishes)
but non-convex: from a poor start they can settle in a wrong minimum, so start them
from RANSAC or a motion prior.

``tuning`` is the default width in units of the per-axis noise sigma: ``c = tuning *
sigma`` gives 95% asymptotic efficiency at an isotropic 3-D Gaussian (the 3-D analogue
of the classic 1-D 1.345 / 2.385 constants), computed as ``eff = A^2 / B`` with
``A = E[w(r) + r w'(r) / 3]``, ``B = E[w(r)^2 r^2] / 3``, ``r ~ chi_3``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Kernel", "get_kernel", "KERNELS", "kernel_names"]


def _wsq_l2(r2: np.ndarray, c: float) -> np.ndarray:
    return np.ones_like(r2)


def _rho_l2(r: np.ndarray, c: float) -> np.ndarray:
    return 0.5 * r * r


def _wsq_huber(r2: np.ndarray, c: float) -> np.ndarray:
    r = np.sqrt(r2)
    np.maximum(r, c, out=r)
    return np.divide(c, r, out=r)


def _rho_huber(r: np.ndarray, c: float) -> np.ndarray:
    return np.where(r <= c, 0.5 * r * r, c * (r - 0.5 * c))


def _wsq_cauchy(r2: np.ndarray, c: float) -> np.ndarray:
    u = r2 * (1.0 / (c * c))
    u += 1.0
    return np.reciprocal(u, out=u)


def _rho_cauchy(r: np.ndarray, c: float) -> np.ndarray:
    return 0.5 * c * c * np.log1p((r / c) ** 2)


def _wsq_gm(r2: np.ndarray, c: float) -> np.ndarray:
    w = _wsq_cauchy(r2, c)
    w *= w
    return w


def _rho_gm(r: np.ndarray, c: float) -> np.ndarray:
    return 0.5 * r * r / (1.0 + (r / c) ** 2)


@dataclass(frozen=True)
class Kernel:
    """A robust kernel: ``weight(r, c)`` for IRLS and ``rho(r, c)`` for reporting.

    ``r``: (N,) residual norms (m); ``c``: width (m). ``tuning``: default ``c / sigma``.
    ``redescending``: influence ``r w(r)`` goes to zero for gross outliers.
    ``weight_sq_fn`` takes *squared* norms (m²), which saves a square root in IRLS.
    """

    name: str
    weight_sq_fn: Callable[[np.ndarray, float], np.ndarray]
    rho_fn: Callable[[np.ndarray, float], np.ndarray]
    tuning: float
    redescending: bool

    def weight(self, r: np.ndarray, c: float) -> np.ndarray:
        """IRLS weight ``w(r; c) = rho'(r) / r`` in [0, 1], same shape as ``r``."""
        if not c > 0:
            raise ValueError(f"kernel width must be > 0, got {c}")
        r = np.asarray(r, dtype=np.float64)
        return self.weight_sq_fn(r * r, float(c))

    def weight_sq(self, r2: np.ndarray, c: float) -> np.ndarray:
        """IRLS weight from squared residual norms ``r2`` (m²); same as ``weight(sqrt(r2), c)``."""
        if not c > 0:
            raise ValueError(f"kernel width must be > 0, got {c}")
        return self.weight_sq_fn(np.asarray(r2, dtype=np.float64), float(c))

    def rho(self, r: np.ndarray, c: float) -> np.ndarray:
        """Kernel cost ``rho(r; c)`` (m²), same shape as ``r``."""
        if not c > 0:
            raise ValueError(f"kernel width must be > 0, got {c}")
        return self.rho_fn(np.asarray(r, dtype=np.float64), float(c))

    def __call__(self, r: np.ndarray, c: float) -> np.ndarray:
        return self.weight(r, c)


_L2 = Kernel("l2", _wsq_l2, _rho_l2, 1.0, False)
_HUBER = Kernel("huber", _wsq_huber, _rho_huber, 1.628, False)
_CAUCHY = Kernel("cauchy", _wsq_cauchy, _rho_cauchy, 2.666, True)
_GM = Kernel("geman_mcclure", _wsq_gm, _rho_gm, 4.337, True)

#: Name (and alias) -> kernel.
KERNELS: dict[str, Kernel] = {
    "l2": _L2,
    "none": _L2,
    "huber": _HUBER,
    "cauchy": _CAUCHY,
    "geman_mcclure": _GM,
    "geman-mcclure": _GM,
    "gm": _GM,
}


def kernel_names() -> list[str]:
    """Canonical kernel names."""
    return sorted({k.name for k in KERNELS.values()})


def get_kernel(kernel: str | Kernel | None) -> Kernel:
    """Look a kernel up by name (case-insensitive; ``None`` means ``"l2"``) or pass one through."""
    if isinstance(kernel, Kernel):
        return kernel
    key = "l2" if kernel is None else str(kernel).strip().lower()
    try:
        return KERNELS[key]
    except KeyError:
        raise ValueError(f"unknown robust kernel {kernel!r}; choose one of {sorted(KERNELS)}") from None
