"""What each file of a results folder holds: its format and its frame (for ``run.json``'s
``files`` entry; the README's output table says the same).

Frames: the *sensor frame* is the frame the reader gives the points in (the Velodyne
for KITTI, the ego vehicle for Argoverse 2); poses are ``T_world_sensor`` with world =
the first processed scan's sensor frame. *KITTI camera 0* is the convention of KITTI's
``poses/XX.txt``: ``T_cam0(0)_cam0(k) = Tr @ T_world_sensor(k) @ inv(Tr)`` with ``Tr =
T_cam0_velo`` from ``calib.txt`` (:func:`flowslam.datasets.kitti.velo_poses_to_cam0`).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from flowslam.trajectory import Trajectory

__all__ = ["in_kitti_convention", "describe_files", "KITTI_FORMAT", "TUM_FORMAT"]

KITTI_FORMAT = "KITTI poses: one line per scan, the 3x4 [R|t] row-major (12 numbers), m; no timestamps"
TUM_FORMAT = "TUM: timestamp(s) tx ty tz qx qy qz qw per scan, m"

SENSOR = "sensor frame: T_world_sensor, world = the first processed scan's sensor frame"
CAMERA0 = ("KITTI camera 0, as poses/XX.txt: T_cam0(0)_cam0(k) = Tr @ T_world_sensor(k) @ inv(Tr), "
           "Tr = T_cam0_velo from calib.txt")
SENSOR_NO_CAMERA = SENSOR + " (the input has no KITTI camera calibration; same as *_kitti_lidar.txt)"
GT_WORLD = "the dataset's ground truth for the processed frames, T_world_sensor in the dataset's GT world"
MAP_WORLD = "world frame (the first processed scan's sensor frame), final poses"


def in_kitti_convention(traj: Trajectory, T_cam0_sensor: np.ndarray | None) -> Trajectory:
    """``traj`` (``T_world_sensor``) as KITTI tools expect it: in camera 0 when the input
    has a KITTI calibration (``T_cam0_sensor`` = ``Tr``), else unchanged (sensor frame)."""
    if T_cam0_sensor is None:
        return traj
    from flowslam.datasets.kitti import velo_poses_to_cam0

    return Trajectory(velo_poses_to_cam0(traj.poses, T_cam0_sensor), traj.timestamps)


def _catalogue(camera0: bool) -> dict[str, tuple[str, str | None]]:
    kitti_frame = CAMERA0 if camera0 else SENSOR_NO_CAMERA
    return {
        "trajectory_tum.txt": (TUM_FORMAT, SENSOR),
        "trajectory_kitti.txt": (KITTI_FORMAT, kitti_frame),
        "trajectory_kitti_lidar.txt": (KITTI_FORMAT, SENSOR),
        "odometry_tum.txt": (TUM_FORMAT, SENSOR + "; the frontend's relative motions chained, no backend"),
        "gt_tum.txt": (TUM_FORMAT, GT_WORLD + " (sensor frame)"),
        "gt_kitti.txt": (KITTI_FORMAT, GT_WORLD + (", KITTI camera 0 (the poses/XX.txt lines)" if camera0
                                                  else " (sensor frame)")),
        "gt_kitti_lidar.txt": (KITTI_FORMAT, GT_WORLD + " (sensor frame)"),
        "metrics.json": ("JSON: APE, RPE, KITTI drift, Table I, end-point error (m, deg)",
                         "trajectory_kitti.txt against gt_kitti.txt (" + ("KITTI camera 0)" if camera0
                                                                         else "sensor frame)")),
        "trajectory_topview.png": ("PNG", "x-y plane of the sensor-frame world (top view)"),
        "static_map.ply": ("binary PLY, float32 x y z intensity (voxel means)", MAP_WORLD),
        "static_map.pcd": ("binary PCD, float32 x y z intensity (PCL PointXYZI)", MAP_WORLD),
        "dynamic_points.ply": ("binary PLY: float32 x y z intensity, int32 instance (-1 none), int32 frame",
                               MAP_WORLD + ", each point at its own scan's pose"),
        "graph.g2o": ("g2o: VERTEX_SE3:QUAT (id = frame index), EDGE_SE3:QUAT T_i_j",
                      SENSOR + " (vertices are the final poses)"),
        "moving_objects.csv": ("CSV: frame, instance, points, centroid (m), velocity and speed (m/s), track id and age, extent (m)", MAP_WORLD),
        "loops.csv": ("CSV: frames i j, ICP fitness, inlier RMSE (m), correction (m, deg)", None),
        "config.yaml": ("YAML: the run's configuration (re-usable with --config)", None),
        "run.json": ("JSON: what happened (frames, speed, errors, files)", None),
    }


def describe_files(names: Iterable[str], camera0: bool) -> dict[str, dict]:
    """``{name: {"format": ..., "frame": ...}}`` for the files ``names`` of a results folder
    (``frame`` None where a file holds no geometry); ``camera0``: the KITTI files are in
    KITTI's camera-0 convention (see module doc). Unknown names get only their suffix."""
    catalogue = _catalogue(camera0)
    out: dict[str, dict] = {}
    for name in names:
        fmt, frame = catalogue.get(name, (name.rpartition(".")[2].upper(), None))
        out[name] = {"format": fmt, "frame": frame}
    return out
