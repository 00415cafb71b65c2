"""Summary statistics of a vector of per-pose (or per-pair) errors, as evo reports them."""

from __future__ import annotations

import numpy as np

__all__ = ["STAT_KEYS", "summary"]

#: Keys of :func:`summary`'s dict, in display order.
STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max", "sse", "n")


def summary(errors) -> dict:
    """Statistics of a 1-D array of errors, in the errors' own unit.

    Returns ``{rmse, mean, median, std, min, max, sse, n}`` as Python floats (``n``
    an int): ``rmse = sqrt(mean(e^2))``, ``std`` the *population* standard
    deviation (``ddof=0``, numpy's and evo's default), ``sse = sum(e^2)`` (so in
    the squared unit, e.g. m^2). An empty input gives ``n = 0`` and ``None``
    for every statistic, so the dict stays JSON-serialisable.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        return {k: (0 if k == "n" else None) for k in STAT_KEYS}
    sq = e * e
    return {
        "rmse": float(np.sqrt(np.mean(sq))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(sq)),
        "n": int(e.size),
    }
