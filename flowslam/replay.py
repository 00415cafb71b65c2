"""Run a frontend once, feed its measurements to several backends.

``RecordingFrontend`` wraps a frontend and keeps each scan's motion measurement
(``T_prev_curr``, covariance, stats; with ``per_point=True`` also the points, as float32,
and the static mask that a mapping stage reads); ``ReplayFrontend``
returns them again in order, so a second backend (or variant) sees exactly the same
odometry without paying for the frontend twice (``flowslam demo``, ``flowslam bench``).
"""

from __future__ import annotations

import numpy as np

from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput

__all__ = ["RecordingFrontend", "ReplayFrontend"]


class RecordingFrontend:
    """Wraps a frontend and keeps its motion measurements (``per_point``: and its points
    and static masks, not the flow or instances)."""

    def __init__(self, inner, per_point: bool = False):
        self.inner, self.name, self.per_point = inner, inner.name, per_point
        self.records: dict[int, FrontendOutput] = {}

    def process(self, frame: Frame) -> FrontendOutput:
        out = self.inner.process(frame)
        kept = {}
        if self.per_point and out.points is not None:
            kept = {"points": np.asarray(out.points, dtype=np.float32), "static_mask": out.static_mask}
        self.records[frame.index] = FrontendOutput(
            index=out.index, T_prev_curr=out.T_prev_curr, covariance=out.covariance, stats=out.stats, **kept
        )
        return out


class ReplayFrontend:
    """Returns recorded measurements in order (same odometry for another backend)."""

    def __init__(self, name: str, records: dict[int, FrontendOutput]):
        self.name, self.records = name, records

    def process(self, frame: Frame) -> FrontendOutput:
        return self.records[frame.index]
