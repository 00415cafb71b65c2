"""Record a run while it happens: a :class:`flowslam.Slam` step listener.

>>> from flowslam.viz.live import LiveRecorder
>>> live = LiveRecorder("run.rrd")                                   # doctest: +SKIP
>>> slam = Slam(config, step_listeners=[live.on_step])              # doctest: +SKIP
>>> ...; slam.save(run_dir); live.finish(slam.result().poses, run_dir)  # doctest: +SKIP

Per-point outputs of step ``k`` (flow, static mask, instances, moving objects) refer to
scan ``k-1`` (:mod:`flowslam.interfaces`), so each scan is logged one step late: with
its labels when the next step brings them, unlabelled when the frontend has none (or it
is the last scan). Poses are the live estimates (``StepResult.T_world_sensor``); GT
(``Frame.gt_pose``, the dataset's GT world) is anchored to the estimate's first pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowslam import geometry
from flowslam.viz.recorder import DYNAMIC, STATIC, RerunRecorder, boxes_of_instances

__all__ = ["LiveRecorder"]


@dataclass
class _Pending:
    index: int
    T_world_sensor: np.ndarray
    points: np.ndarray


class LiveRecorder:
    """Turns each :class:`flowslam.slam.StepResult` into :class:`RerunRecorder` calls."""

    def __init__(self, path: str | Path, **recorder_options):
        self.recorder = RerunRecorder(path, **recorder_options)
        self._pending: _Pending | None = None
        self._T_world_gtworld: np.ndarray | None = None

    def on_step(self, step) -> None:
        rec = self.recorder
        frame = step.frame
        rec.pose(step.index, step.T_world_sensor, self._gt_in_world(step))
        for loop in step.loops:
            rec.loop(step.index, loop.i, loop.j)
        pending, self._pending = self._pending, None
        if pending is not None:
            if step.points is not None and step.static_mask is not None:
                self._labelled_scan(pending, step)
            else:
                rec.scan(pending.index, pending.T_world_sensor, pending.points)
        if frame is not None:
            self._pending = _Pending(step.index, np.asarray(step.T_world_sensor), frame.points)

    def _gt_in_world(self, step) -> np.ndarray | None:
        gt = None if step.frame is None else step.frame.gt_pose
        if gt is None:
            return None
        if self._T_world_gtworld is None:  # first poses anchored together
            self._T_world_gtworld = np.asarray(step.T_world_sensor) @ geometry.inv(gt)
        return self._T_world_gtworld @ gt

    def _labelled_scan(self, prev: _Pending, step) -> None:
        """Scan ``prev`` with the labels, flow and objects that ``step`` found for it."""
        from flowslam.moving_objects import ego_compensated_flow

        rec, T = self.recorder, prev.T_world_sensor
        points = np.asarray(step.points, dtype=np.float64)
        dynamic = ~np.asarray(step.static_mask, dtype=bool)
        rec.scan(prev.index, T, points, np.where(dynamic, DYNAMIC, STATIC))
        if step.flow is not None and step.T_prev_curr is not None:
            moved = ego_compensated_flow(points, step.flow, step.T_prev_curr)  # sensor frame prev, m
            rec.flow(prev.index, geometry.transform_points(T, points), moved @ T[:3, :3].T, dynamic)
        if step.moving_objects and step.instance_ids is not None:
            ids = [o.instance_id for o in step.moving_objects]
            centres, halves = boxes_of_instances(points[dynamic], np.asarray(step.instance_ids)[dynamic], ids)
            velocities = np.array([o.velocity for o in step.moving_objects]) @ T[:3, :3].T
            q = geometry.to_quat_xyzw(T).reshape(4)
            rec.objects(prev.index, geometry.transform_points(T, centres), halves, velocities, ids,
                        np.tile(q, (len(ids), 1)))

    def finish(self, final_poses: np.ndarray | None = None, run_dir: str | Path | None = None) -> Path:
        """Log the last scan, the final trajectory (``T_world_sensor`` (N,4,4)) and the maps
        of the results folder ``run_dir`` (world frame); close the file and return its path."""
        from flowslam.viz.from_results import log_maps

        rec = self.recorder
        if self._pending is not None:
            rec.scan(self._pending.index, self._pending.T_world_sensor, self._pending.points)
            self._pending = None
        if final_poses is not None and len(final_poses):
            rec.final_trajectory(final_poses)
        if run_dir is not None:
            log_maps(rec, Path(run_dir))
        return rec.close()
