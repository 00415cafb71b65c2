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
from flowslam.slam import RunResult, Slam

__all__ = ["RunResult", "drive", "run_pipeline"]


def drive(
    slam: Slam, dataset: Dataset, frames: range | None = None, on_frame: Callable[[int, float], None] | None = None
) -> RunResult:
    """Feed ``frames`` (dataset indices, default all) of ``dataset`` to ``slam`` in order;
    ``on_frame(k, seconds)`` after each (progress bars; seconds include the read).
    Exceptions, including ``KeyboardInterrupt``, end the loop and are stored in the
    result instead of propagating."""
    frames = range(len(dataset)) if frames is None else frames
    for k, index in enumerate(frames):
        start = time.perf_counter()
        try:
            slam.process(dataset[index], started=start)
        except (Exception, KeyboardInterrupt) as error:  # keep what is done, report after writing
            slam.stopped(error, index)
            break
        if on_frame is not None:
            on_frame(k, time.perf_counter() - start)
    return slam.result()


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
