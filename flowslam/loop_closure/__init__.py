"""Loop closure: place recognition (Scan Context) and geometric verification (ICP).

- :mod:`.scan_context` the descriptor, ring key and column-shift distance (yaw);
- :mod:`.candidates` ring-key KD-tree over the scans old enough to close a loop with;
- :mod:`.verification` Open3D point-to-plane ICP with fitness / RMSE gates, covariance;
- :mod:`.detector` :class:`ScanContextLoopCloser`, the ``LoopCloser`` of ``s-loam``.

Options: ``flowslam.config.loop_closure`` (``loop_closure:`` in the run config).
Importing this package imports neither Open3D nor GTSAM.
"""

from __future__ import annotations

from flowslam.config.loop_closure import LoopClosureConfig

__all__ = ["make_loop_closer"]


def make_loop_closer(config: LoopClosureConfig):
    """The loop closer for these options, or None when loop closure is off (``a-loam``)."""
    if not config.enabled:
        return None
    from .detector import ScanContextLoopCloser

    return ScanContextLoopCloser(config)
