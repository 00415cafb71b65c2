"""Loop closure: place recognition (Scan Context) and geometric verification (ICP).

- :mod:`.scan_context` the descriptor, ring key and column-shift distance (yaw);
- :mod:`.candidates` ring-key KD-tree over the scans old enough to close a loop with;
- :mod:`.verification` Open3D point-to-plane ICP with fitness / RMSE gates, covariance;
- :mod:`.detector` :class:`ScanContextLoopCloser`, the ``LoopCloser`` of ``s-loam``;
- :mod:`.config` the options (``isam2.loop_closure`` in the run config).

Importing this package imports neither Open3D nor GTSAM.
"""

from __future__ import annotations

from typing import Any

from .config import LoopClosureConfig, ScanContextConfig, VerificationConfig

__all__ = ["LoopClosureConfig", "ScanContextConfig", "VerificationConfig", "make_loop_closer"]


def make_loop_closer(config: Any):
    """The loop closer for a run config, or None for the odometry-only ``a-loam`` variant.

    ``config`` is a ``PipelineConfig`` (its ``isam2`` section; defaults if it has
    none) or an ``Isam2Config`` itself.
    """
    from flowslam.backends.isam2 import Isam2Config

    isam2 = config if isinstance(config, Isam2Config) else getattr(config, "isam2", None) or Isam2Config()
    if isam2.variant == "a-loam":
        return None
    from .detector import ScanContextLoopCloser

    return ScanContextLoopCloser(isam2.loop_closure)
