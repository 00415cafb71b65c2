"""flowslam: LiDAR SLAM with scene flow as odometry on a GTSAM factor graph.

Core modules: ``geometry`` (SE(3), the ``T_a_b`` convention), ``registration``
(robust Kabsch / IRLS / RANSAC), ``trajectory`` (trajectory files),
``evaluation`` (APE/RPE/KITTI drift), ``pipeline`` (frontend -> backend loop).
Plug-ins: ``flowslam.frontends``, ``flowslam.backends``, ``flowslam.datasets``.
"""

__version__ = "0.1.0"
