"""The run loop: dataset -> frontend -> backend, one scan at a time.

Thin on purpose (like KISS-ICP's pipeline): it reads each frame, hands it to the
frontend, passes the measurement to the backend, and records timings. It never
loses work: any error (bad input in frame k, a crash, Ctrl-C) stops the loop and
is kept in ``RunResult.error`` so the caller can still write the trajectory of
the frames processed so far, then report the error.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from flowslam.frame import Dataset, Frame
from flowslam.interfaces import Backend, Frontend, FrontendOutput, LoopCloser, LoopClosure
from flowslam.trajectory import Trajectory


@dataclass
class RunResult:
    """Outcome of a run. ``poses`` are ``T_world_sensor`` with world = first processed scan."""

    indices: list[int] = field(default_factory=list)
    """Dataset frame index of each processed scan."""
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
    """Dataset index of the scan during which ``error`` happened."""

    @property
    def trajectory(self) -> Trajectory:
        return Trajectory(self.poses, np.asarray(self.timestamps, dtype=np.float64))

    @property
    def frames_per_second(self) -> float:
        total = float(np.sum(self.seconds_per_frame))
        return len(self.seconds_per_frame) / total if total > 0 else float("nan")


def run_pipeline(
    dataset: Dataset,
    frontend: Frontend,
    backend: Backend,
    frames: range | None = None,
    on_frame: Callable[[int, float], None] | None = None,
    loop_closer: LoopCloser | None = None,
    on_output: Callable[[Frame, FrontendOutput], None] | None = None,
) -> RunResult:
    """Process ``frames`` (dataset indices, default all) in order.

    Per scan: frontend -> ``backend.add_odometry`` -> (if ``loop_closer``) the scan
    and its current pose estimate go to the loop closer, and every loop it
    returns goes to ``backend.add_loop``. ``on_output(frame, output)`` sees each
    frontend output (e.g. to build the static map); ``on_frame(k, seconds)`` is
    called after each scan (for progress bars).
    Exceptions, including ``KeyboardInterrupt``, end the loop and are stored in
    the result instead of propagating.
    """
    frames = range(len(dataset)) if frames is None else frames
    result = RunResult()
    for k, index in enumerate(frames):
        start = time.perf_counter()
        try:
            frame = dataset[index]
            out = frontend.process(frame)
            backend.add_odometry(index, out.T_prev_curr, out.covariance)
            if on_output is not None:
                on_output(frame, out)
            if loop_closer is not None:
                T_world_sensor = backend.latest_pose()
                for loop in loop_closer.add_scan(index, frame.points, T_world_sensor):
                    backend.add_loop(loop.i, loop.j, loop.T_i_j, loop.covariance)
                    result.loops.append(loop)
        except (Exception, KeyboardInterrupt) as error:  # keep what is done, report after writing
            result.error, result.failed_index = error, index
            break
        if out.T_prev_curr is not None:
            result.odometry.append(out.T_prev_curr)
        result.indices.append(index)
        result.timestamps.append(float(frame.timestamp))
        result.frontend_stats.append(out.stats)
        seconds = time.perf_counter() - start
        result.seconds_per_frame.append(seconds)
        if on_frame is not None:
            on_frame(k, seconds)
    # A backend that failed half-way through a scan may hold one pose too many.
    result.poses = backend.trajectory()[: len(result.indices)] if result.indices else np.zeros((0, 4, 4))
    return result
