"""The streaming API: one object that takes scans one at a time, for other SLAM stacks.

>>> from flowslam import Slam
>>> slam = Slam(load_config(frontend="ssf", backend="isam2"))        # doctest: +SKIP
>>> for points, stamp in scans:                                      # doctest: +SKIP
...     step = slam.register_frame(points, stamp)
...     step.T_world_sensor, step.static_mask, step.moving_objects
>>> slam.trajectory(); slam.save("results/my_run")                   # doctest: +SKIP

``Slam`` owns the frontend, the backend, the loop closer (when the backend takes loops
and ``loop_closure.enabled``), the static map and the moving-objects log, exactly as
``flowslam run`` builds them; ``flowslam run`` drives the same object over a dataset
(:func:`flowslam.pipeline.run_pipeline`), so a stream and a run give the same result.

Frames and units: ``points`` (N,3) in the sensor frame of the scan (m), ``timestamp``
and ``point_times`` in seconds; poses ``T_world_sensor`` (world = the first scan's
sensor frame); ``T_prev_curr`` maps the new scan into the previous one. Per-point
outputs of a step (``flow``, ``static_mask``, ``instance_ids``) refer to the points of
the **previous** scan (``step.points``), as in :mod:`flowslam.interfaces`.
"""

from __future__ import annotations

import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from flowslam.config import PipelineConfig
from flowslam.errors import InputError
from flowslam.frame import Frame, sanitize_frame
from flowslam.interfaces import Backend, Frontend, FrontendOutput, LoopCloser, LoopClosure
from flowslam.trajectory import Trajectory

__all__ = ["Slam", "StepResult", "RunResult"]

Listener = Callable[[Frame, FrontendOutput], None]


@dataclass
class RunResult:
    """What a sequence of steps produced. ``poses`` are ``T_world_sensor`` with world =
    first processed scan."""

    indices: list[int] = field(default_factory=list)
    """Frame index of each processed scan."""
    timestamps: list[float] = field(default_factory=list)
    """Scan timestamps (s)."""
    seconds_per_frame: list[float] = field(default_factory=list)
    """Wall time of read + frontend + backend for each scan (s)."""
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    odometry: list[np.ndarray] = field(default_factory=list)
    """The frontend's relative motions ``T_prev_curr`` (one fewer than scans)."""
    frontend_stats: list[dict] = field(default_factory=list)
    loops: list[LoopClosure] = field(default_factory=list)
    """Loop closures accepted and passed to the backend."""
    error: BaseException | None = None
    failed_index: int | None = None
    """Index of the scan during which ``error`` happened."""

    @property
    def trajectory(self) -> Trajectory:
        return Trajectory(self.poses, np.asarray(self.timestamps, dtype=np.float64))

    @property
    def frames_per_second(self) -> float:
        total = float(np.sum(self.seconds_per_frame))
        return len(self.seconds_per_frame) / total if total > 0 else float("nan")


@dataclass
class StepResult:
    """What one scan gave (see module doc for frames)."""

    index: int
    timestamp: float
    T_world_sensor: np.ndarray
    """This scan's pose as the backend estimates it right after the scan (4x4)."""
    output: FrontendOutput
    """The frontend's measurement: ``T_prev_curr``, covariance and per-point outputs."""
    loops: list[LoopClosure]
    """Loop closures this scan closed (already in the backend)."""
    moving_objects: list
    """``MovingObject``s of the previous scan that this step found (sensor frame of that scan)."""
    frame: Frame | None = None
    """The scan of this step as processed (sensor frame; ``gt_pose`` where the dataset has GT)."""

    @property
    def T_prev_curr(self) -> np.ndarray | None:
        return self.output.T_prev_curr

    @property
    def covariance(self) -> np.ndarray | None:
        """6x6, Pose3 tangent of ``T_prev_curr`` ([rotation rad, translation m])."""
        return self.output.covariance

    @property
    def points(self) -> np.ndarray | None:
        """The previous scan's points, which the per-point outputs refer to."""
        return self.output.points

    @property
    def flow(self) -> np.ndarray | None:
        return self.output.flow

    @property
    def static_mask(self) -> np.ndarray | None:
        return self.output.static_mask

    @property
    def instance_ids(self) -> np.ndarray | None:
        return self.output.instance_ids


_FROM_CONFIG = object()


class Slam:
    """flowslam one scan at a time (module doc). ``frontend``/``backend`` instances replace
    the ones ``config`` names; ``loop_closer`` replaces the configured one (``None``: no
    loop closure); ``scan_to_map`` replaces the configured mapping stage (``None``: none);
    ``outputs=False`` keeps no static map or objects log (for callers
    that only want poses); ``listeners`` see every ``(frame, frontend output)``,
    ``step_listeners`` every :class:`StepResult` (after its loop closures; e.g. the 3-D
    recorder of :mod:`flowslam.viz.live`)."""

    def __init__(
        self,
        config: PipelineConfig | None = None,
        *,
        frontend: Frontend | None = None,
        backend: Backend | None = None,
        loop_closer: LoopCloser | None = _FROM_CONFIG,  # type: ignore[assignment]
        outputs: bool = True,
        listeners: Iterable[Listener] = (),
        scan_to_map=_FROM_CONFIG,
        step_listeners: Iterable[Callable[["StepResult"], None]] = (),
    ):
        from flowslam.registry import make_backend, make_frontend

        self.config = config or PipelineConfig()
        self.frontend = frontend or make_frontend(self.config.frontend, self.config)
        self.backend = backend or make_backend(self.config.backend, self.config)
        if loop_closer is _FROM_CONFIG:
            loop_closer = None
            if getattr(self.backend, "accepts_loops", False):
                from flowslam.loop_closure import make_loop_closer

                loop_closer = make_loop_closer(self.config.loop_closure)
        self.loop_closer = loop_closer
        self.scan_to_map = self._make_scan_to_map() if scan_to_map is _FROM_CONFIG else scan_to_map
        self._prev_frame: Frame | None = None
        self.map = self.objects = None
        if outputs:
            from flowslam.mapping import StaticMapBuilder
            from flowslam.moving_objects import MovingObjectsLog

            out = self.config.output
            if out.static_map:
                self.map = StaticMapBuilder(out.map_voxel_size, out.map_points_per_frame)
            self.objects = MovingObjectsLog(min_track_scans=out.min_track_scans)
        self.listeners = [sink.on_output for sink in (self.map, self.objects) if sink is not None] + list(listeners)
        self.step_listeners = list(step_listeners)
        self._result = RunResult()

    # -- input ---------------------------------------------------------------------------

    def register_frame(
        self,
        points: np.ndarray,
        timestamp: float,
        point_times: np.ndarray | None = None,
        intensity: np.ndarray | None = None,
    ) -> StepResult:
        """Add the next scan: ``points`` (N,3) sensor frame (m), ``timestamp`` (s, after the
        previous scan's), optional per-point ``point_times`` (s) and ``intensity``.
        Non-finite and implausibly far points are dropped as the readers drop them; a
        scan with too few points left, or a timestamp not after the last, is an
        ``InputError`` (the state is unchanged, so the caller can skip the scan)."""
        timestamp = float(timestamp)
        last = self._result.timestamps[-1] if self._result.timestamps else None
        if not np.isfinite(timestamp) or (last is not None and timestamp <= last):
            raise InputError("register_frame", f"timestamp {timestamp!r} is not after the last scan's ({last})")
        index = self._result.indices[-1] + 1 if self._result.indices else 0
        frame = Frame(index=index, timestamp=timestamp, points=np.asarray(points, dtype=np.float64),
                      intensity=intensity, point_times=point_times, source=f"register_frame #{index}")
        frame = sanitize_frame(frame, max_coordinate_m=self.config.dataset.max_coordinate_m)
        return self.process(frame)

    def process(self, frame: Frame, started: float | None = None) -> StepResult:
        """Add a scan as a dataset reader gives it (already sanitised); ``frame.index``
        increasing. ``started`` (``time.perf_counter()``) is when the step's work began,
        e.g. before reading the scan (default: now). An exception leaves the step
        unrecorded (the backend may hold one pose more; :meth:`result` trims it)."""
        start = time.perf_counter() if started is None else started
        out = self.frontend.process(frame)
        covariance = out.covariance
        if self.scan_to_map is not None and covariance is not None:  # the map factors lead (config doc)
            covariance = covariance * self.config.mapping.odometry_covariance_scale
        self.backend.add_odometry(frame.index, out.T_prev_curr, covariance)
        n_objects = len(self.objects.objects) if self.objects is not None else 0
        for listener in self.listeners:
            listener(frame, out)
        if self.scan_to_map is not None:
            self._register_to_map(frame, out)
        loops = self._close_loops(frame)
        r = self._result
        if out.T_prev_curr is not None:
            r.odometry.append(out.T_prev_curr)
        r.indices.append(frame.index)
        r.timestamps.append(float(frame.timestamp))
        r.frontend_stats.append(out.stats)
        r.seconds_per_frame.append(time.perf_counter() - start)
        objects = self.objects.objects[n_objects:] if self.objects is not None else []
        step = StepResult(frame.index, float(frame.timestamp), self.backend.latest_pose(), out, loops, objects, frame)
        for listener in self.step_listeners:
            listener(step)
        return step

    def _close_loops(self, frame: Frame) -> list[LoopClosure]:
        if self.loop_closer is None:
            return []
        before = self.backend.latest_pose()
        found = self.loop_closer.add_scan(frame.index, frame.points, before)
        for loop in found:
            self.backend.add_loop(loop.i, loop.j, loop.T_i_j, loop.covariance)
            self._result.loops.append(loop)
        if found and self.scan_to_map is not None:
            self.scan_to_map.moved(before, self.backend.latest_pose())
        return found

    def _make_scan_to_map(self):
        """The mapping stage (:mod:`flowslam.scan_to_map`) when ``mapping.enabled`` and the
        backend takes map factors (``add_map_factor``: graph backends), else None. (A user
        who asks for it with a backend without factors gets an error from
        :func:`flowslam.run.check_requested_options`.)"""
        if not self.config.mapping.enabled or not hasattr(self.backend, "add_map_factor"):
            return None
        from flowslam.scan_to_map import ScanToMap

        return ScanToMap(self.config.mapping)

    def _register_to_map(self, frame: Frame, out: FrontendOutput) -> None:
        """Scan k-1 to the local map, one scan late for every frontend: a segmenting
        frontend's static mask of scan k-1 comes with scan k (``out.points``); others'
        scans are used whole. Its factor goes to the backend; ``mapping_ms`` to the stats."""
        prev, self._prev_frame = self._prev_frame, frame
        if prev is None:
            return
        points, mask = (out.points, out.static_mask) if out.points is not None else (prev.points, None)
        factor = self.scan_to_map.step(prev.index, points, mask, self.backend.estimate)
        if factor is not None:
            self.backend.add_map_factor(factor.anchor, factor.scan, factor.T_anchor_scan, factor.covariance)
        out.stats["mapping_ms"] = self.scan_to_map.stats.seconds[-1] * 1e3

    # -- output --------------------------------------------------------------------------

    def result(self) -> RunResult:
        """The steps so far with the backend's current poses (a snapshot)."""
        r = self._result
        n = len(r.indices)
        poses = self.backend.trajectory()[:n] if n else np.zeros((0, 4, 4))
        return RunResult(list(r.indices), list(r.timestamps), list(r.seconds_per_frame), poses,
                         list(r.odometry), list(r.frontend_stats), list(r.loops), r.error, r.failed_index)

    def trajectory(self) -> Trajectory:
        """``T_world_sensor`` of every scan so far, with timestamps (s)."""
        return self.result().trajectory

    def save(self, results_dir: str | Path, *, gt: Trajectory | None = None, metrics: dict | None = None,
             run_info: dict | None = None, T_cam0_sensor: np.ndarray | None = None) -> list[Path]:
        """Write a results folder (the files of ``flowslam run``; README) into
        ``results_dir`` (created if missing): every file atomically, ``run.json`` last.
        ``run_info`` adds to what ``run.json`` says; ``run.json``'s ``files`` states each
        file's format and frame. ``T_cam0_sensor``: KITTI's ``Tr`` (``calib.txt``, sensor
        into camera 0) puts ``trajectory_kitti.txt``/``gt_kitti.txt`` in KITTI's camera-0
        convention, as ``poses/XX.txt`` (``gt`` stays ``T_world_sensor``, sensor frame)."""
        from flowslam.output_files import describe_files
        from flowslam.results import make_results_folder, write_atomic, write_json, write_results

        results_dir = make_results_folder(results_dir)
        result = self.result()
        tracks = None
        if self.objects is not None and result.indices:
            tracks = self.objects.tracks(result.poses, result.indices)
        written = write_results(results_dir, result, self.config, gt, metrics, T_cam0_sensor, tracks)
        if result.indices and getattr(self.backend, "exports_graph", False):
            written.append(write_atomic(results_dir / "graph.g2o", self.backend.write_g2o))
        if result.indices and self.map is not None and self.map.n_points:
            for name in ("static_map.ply", "static_map.pcd"):  # one build (cached), two formats
                written.append(write_atomic(results_dir / name,
                                            lambda tmp: self.map.write(tmp, result.poses, result.indices)))
            if self.map.dynamic.n_points:
                written.append(write_atomic(results_dir / "dynamic_points.ply",
                                            lambda tmp: self.map.dynamic.write(tmp, result.poses, result.indices)))
        if result.indices and self.objects is not None and self.objects.objects:
            written.append(write_atomic(results_dir / "moving_objects.csv",
                                        lambda tmp: self.objects.write_csv(tmp, result.poses, result.indices)))
        info = self.describe(result) | (run_info or {})
        names = [path.name for path in written] + ["run.json"]
        info["files"] = describe_files(names, camera0=T_cam0_sensor is not None)
        written.append(write_json(results_dir / "run.json", info))
        return written

    def describe(self, result: RunResult | None = None) -> dict:
        """``run.json``'s account of the steps: parts, frames, speed, why it stopped,
        fallbacks, loop closures, backend timings."""
        from flowslam import __version__
        from flowslam.fallbacks import summarize_fallbacks
        from flowslam.signals import describe_stop

        r = result or self.result()
        return {
            "flowslam_version": __version__,
            "python": platform.python_version(),
            "frontend": getattr(self.frontend, "name", type(self.frontend).__name__),
            "frontend_info": getattr(self.frontend, "info", None),
            "backend": getattr(self.backend, "name", type(self.backend).__name__),
            "loop_closure": self.loop_closer is not None,
            "frames_processed": len(r.indices),
            "first_index": r.indices[0] if r.indices else None,
            "complete": r.error is None,
            "frames_per_second": r.frames_per_second,
            "median_ms_per_frame": float(np.median(r.seconds_per_frame) * 1e3) if r.seconds_per_frame else None,
            "error": None if r.error is None else describe_stop(r.error),
            "failed_index": r.failed_index,
            "fallbacks": summarize_fallbacks(r.frontend_stats),
            "loop_closures": len(r.loops),
            "loops": [dict(i=lc.i, j=lc.j, fitness=lc.fitness, rmse_m=lc.inlier_rmse, **lc.info) for lc in r.loops],
            "backend_stats": getattr(self.backend, "stats", None),
            "mapping": None if self.scan_to_map is None else self.scan_to_map.stats.as_dict(),
        }

    def stopped(self, error: BaseException, index: int) -> None:
        """Record that the run stopped on ``error`` during scan ``index`` (for ``run.json``)."""
        self._result.error, self._result.failed_index = error, index
