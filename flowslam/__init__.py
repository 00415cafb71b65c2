"""flowslam: LiDAR SLAM with scene flow as odometry on a GTSAM factor graph.

Core modules: ``geometry`` (SE(3), the ``T_a_b`` convention), ``registration``
(robust Kabsch / IRLS / RANSAC), ``trajectory`` (trajectory files),
``evaluation`` (APE/RPE/KITTI drift), ``slam`` (the streaming API, :class:`Slam`),
``pipeline`` (a dataset driven through it), ``run`` (``flowslam run`` as a call).
Plug-ins: ``flowslam.frontends``, ``flowslam.backends``, ``flowslam.datasets``.
"""

__version__ = "0.1.0"

__all__ = ["Slam", "load_config", "__version__"]


def __getattr__(name: str):
    """``flowslam.Slam`` and ``flowslam.load_config`` without importing them at start-up."""
    if name == "Slam":
        from flowslam.slam import Slam

        return Slam
    if name == "load_config":
        from flowslam.config import load_config

        return load_config
    raise AttributeError(f"module 'flowslam' has no attribute {name!r}")
