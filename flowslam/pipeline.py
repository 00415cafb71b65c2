"""The run loop: dataset -> :class:`flowslam.slam.Slam`, one scan at a time.

Thin on purpose (like KISS-ICP's pipeline): it reads each frame and hands it to the
``Slam`` object (frontend -> backend -> loop closer -> output sinks), recording
timings. It never loses work: any error (bad input in frame k, a crash, Ctrl-C,
SIGTERM under :func:`flowslam.signals.terminate_as_interrupt`) stops the loop and is
kept in ``RunResult.error`` so the caller can still write the trajectory of the frames
processed so far, then report the error.
"""

from __future__ import annotations

import time
from typing import Callable

from flowslam.frame import Dataset, Frame
from flowslam.interfaces import Backend, Frontend, FrontendOutput, LoopCloser
from flowslam.signals import Terminated, sigterm_at_safe_points, stop_behind
from flowslam.slam import RunResult, Slam

__all__ = ["RunResult", "drive", "run_pipeline"]


def drive(
    slam: Slam, dataset: Dataset, frames: range | None = None, on_frame: Callable[[int, float], None] | None = None
) -> RunResult:
    """Feed ``frames`` (dataset indices, default all) of ``dataset`` to ``slam`` in order;
    ``on_frame(k, seconds)`` after each (progress bars; seconds include the read).
    Exceptions, including ``KeyboardInterrupt``, end the loop and are stored in the
    result instead of propagating, also those raised between two scans (in ``on_frame``, or a
    signal handled at the loop's own step); the scan then said to have stopped the run is
    the first one not processed (the last one when all were). Under
    :func:`~flowslam.signals.terminate_as_interrupt` (``flowslam run``), SIGTERM stops the
    loop when the scan in progress is done. A frontend with an
    ``upcoming(frame)`` method is told the next scan before it processes the current one
    (read one step ahead: its work on the next scan may start early, e.g. ``ssf``'s network)."""
    frames = range(len(dataset)) if frames is None else frames
    with sigterm_at_safe_points() as stop_requested:
        _loop(slam, dataset, frames, on_frame, stop_requested)
        try:
            stop_requested()  # left only when the scan that failed got it: the run stops for that failure
        except Terminated:
            pass
    return slam.result()


def _loop(slam: Slam, dataset: Dataset, frames, on_frame, stop_requested: Callable[[], None]) -> None:
    """:func:`drive`'s loop; ``stop_requested()`` raises a SIGTERM that came during the last
    scan (:func:`~flowslam.signals.sigterm_at_safe_points`), before the next one starts and
    after the last one."""
    upcoming = getattr(slam.frontend, "upcoming", None)
    ahead: Frame | None = None  # frames[k], read one step early for the frontend's ``upcoming``
    try:
        for k, index in enumerate(frames):
            start = time.perf_counter()
            try:
                stop_requested()
                frame, ahead = (ahead if ahead is not None else dataset[index]), None
                if upcoming is not None and k + 1 < len(frames):
                    ahead = _read_ahead(dataset, frames[k + 1])
                    if ahead is not None:
                        upcoming(ahead)
                slam.process(frame, started=start)
            except (Exception, KeyboardInterrupt) as error:  # keep what is done, report after writing
                slam.stopped(stop_behind(error), index)  # a signal that surfaced as another error is the signal
                break
            if on_frame is not None:
                on_frame(k, time.perf_counter() - start)
        else:
            stop_requested()
    except (Exception, KeyboardInterrupt) as error:  # between two scans: the progress callback, the loop itself
        done = len(slam.result().indices)
        slam.stopped(stop_behind(error), frames[min(done, len(frames) - 1)])  # the first scan not processed


def _read_ahead(dataset: Dataset, index: int) -> Frame | None:
    """Scan ``index`` read early, or None when reading it fails: the loop then reads it again
    in its turn, and the error stops the run there (the scans before it are processed)."""
    try:
        return dataset[index]
    except Exception:
        return None


def run_pipeline(
    dataset: Dataset,
    frontend: Frontend,
    backend: Backend,
    frames: range | None = None,
    on_frame: Callable[[int, float], None] | None = None,
    loop_closer: LoopCloser | None = None,
    on_output: Callable[[Frame, FrontendOutput], None] | None = None,
) -> RunResult:
    """Process ``frames`` with these parts only (no mapping stage, no output sinks;
    ``on_output(frame, output)`` sees each frontend output): :func:`drive` over a bare
    :class:`Slam`."""
    slam = Slam(frontend=frontend, backend=backend, loop_closer=loop_closer, scan_to_map=None, outputs=False,
                listeners=[on_output] if on_output is not None else [])
    return drive(slam, dataset, frames, on_frame)
