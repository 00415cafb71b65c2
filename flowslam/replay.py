"""Run a frontend once, feed its measurements to several backends.

``RecordingFrontend`` wraps a frontend and keeps each scan's motion measurement
(``T_prev_curr``, covariance, stats; not the per-point outputs); ``ReplayFrontend``
returns them again in order, so a second backend (or variant) sees exactly the same
odometry without paying for the frontend twice (``flowslam demo``, ``flowslam bench``).
"""

from __future__ import annotations

from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput

__all__ = ["RecordingFrontend", "ReplayFrontend"]


class RecordingFrontend:
    """Wraps a frontend and keeps its motion measurements (not its per-point outputs)."""

    def __init__(self, inner):
        self.inner, self.name = inner, inner.name
        self.records: dict[int, FrontendOutput] = {}

    def process(self, frame: Frame) -> FrontendOutput:
        out = self.inner.process(frame)
        self.records[frame.index] = FrontendOutput(
            index=out.index, T_prev_curr=out.T_prev_curr, covariance=out.covariance, stats=out.stats
        )
        return out


class ReplayFrontend:
    """Returns recorded measurements in order (same odometry for another backend)."""

    def __init__(self, name: str, records: dict[int, FrontendOutput]):
        self.name, self.records = name, records

    def process(self, frame: Frame) -> FrontendOutput:
        return self.records[frame.index]
