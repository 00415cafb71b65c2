"""Run a frontend once, feed its measurements to several backends.

``RecordingFrontend`` wraps a frontend and keeps each scan's motion measurement
(``T_prev_curr``, covariance, stats; with ``per_point=True`` also the static mask that
a mapping stage reads, and the points it refers to); ``ReplayFrontend``
returns them again in order, so a second backend (or variant) sees exactly the same
odometry without paying for the frontend twice (``flowslam demo``, ``flowslam bench``).
Points that are the previous scan's own array (``ssf``, ``gt``) are not copied: the
replay takes them from the previous frame it is given, which is the same scan.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput

__all__ = ["RecordingFrontend", "ReplayFrontend"]


class RecordingFrontend:
    """Wraps a frontend and keeps its motion measurements (``per_point``: and its points
    and static masks, not the flow or instances)."""

    def __init__(self, inner, per_point: bool = False):
        self.inner, self.name, self.per_point = inner, inner.name, per_point
        if hasattr(inner, "upcoming"):  # the run loop's read-ahead reaches the inner frontend (ssf's two threads)
            self.upcoming = inner.upcoming
        self.records: dict[int, FrontendOutput] = {}
        self.points_from_previous: set[int] = set()
        """Steps whose ``points`` are the previous frame's (not stored; see module doc)."""
        self._previous_points = None

    def process(self, frame: Frame) -> FrontendOutput:
        out = self.inner.process(frame)
        kept = {}
        if self.per_point and out.points is not None:
            kept["static_mask"] = out.static_mask
            if out.points is self._previous_points:
                self.points_from_previous.add(frame.index)
            else:
                kept["points"] = np.asarray(out.points, dtype=np.float32)
        self._previous_points = frame.points
        self.records[frame.index] = FrontendOutput(
            index=out.index, T_prev_curr=out.T_prev_curr, covariance=out.covariance, stats=out.stats, **kept
        )
        return out


class ReplayFrontend:
    """Returns recorded measurements in order (same odometry for another backend);
    ``points_from_previous``: :attr:`RecordingFrontend.points_from_previous`."""

    def __init__(self, name: str, records: dict[int, FrontendOutput], points_from_previous=frozenset()):
        self.name, self.records, self.points_from_previous = name, records, points_from_previous
        self._previous_points = None

    def process(self, frame: Frame) -> FrontendOutput:
        out = self.records[frame.index]
        if frame.index in self.points_from_previous:
            out = dataclasses.replace(out, points=self._previous_points)
        self._previous_points = frame.points
        return out

    @classmethod
    def of(cls, recorder: RecordingFrontend) -> "ReplayFrontend":
        """The replay of a recording."""
        return cls(recorder.name, recorder.records, frozenset(recorder.points_from_previous))
