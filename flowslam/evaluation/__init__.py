"""Trajectory evaluation: APE, RPE, KITTI drift, SSF-PAN Table I statistics.

Estimates and ground truths are ``flowslam.trajectory.Trajectory`` objects
(or (N,4,4) stacks of ``T_world_sensor``). Pair them with :func:`associate`
(by timestamp, or by index), then compute:

- :func:`ape` absolute pose error after Umeyama / origin alignment (evo's ``evo_ape``);
- :func:`rpe` relative pose error per frame step or per metres travelled (evo's ``evo_rpe``);
- :func:`kitti_drift` the KITTI devkit's segment drift (t in %, r in deg/m and deg/100 m);
- :func:`table1` the RPE(1) RMSE / SSE / STD of SSF-PAN's Table I (m and deg);
- :func:`evaluate` all of the above as one JSON-serialisable dict, :func:`render_table` for printing.

Metres and radians internally; result keys name their unit (``trans_m``, ``rot_deg``, ...).
The numbers agree with evo (tested), but no evo code is used: evo is GPL-3.0 and only a
test oracle here.
"""

from .align import align_origin, align_trajectory, apply_alignment, umeyama
from .ape import ape, ape_errors
from .associate import associate, match_timestamps
from .kitti_drift import KITTI_LENGTHS, kitti_drift, segment_errors
from .report import evaluate, render_table
from .rpe import accumulated_distances, relative_errors, rpe, rpe_errors, rpe_pairs
from .stats import summary
from .table1 import table1

__all__ = [
    "associate",
    "match_timestamps",
    "umeyama",
    "apply_alignment",
    "align_trajectory",
    "align_origin",
    "summary",
    "ape",
    "ape_errors",
    "rpe",
    "rpe_errors",
    "rpe_pairs",
    "relative_errors",
    "accumulated_distances",
    "KITTI_LENGTHS",
    "kitti_drift",
    "segment_errors",
    "table1",
    "evaluate",
    "render_table",
]
