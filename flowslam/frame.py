"""The common frame interface every dataset reader returns, and the base class of readers.

Frames and units
----------------
- ``points``: (N,3) float64, metres, in the *sensor frame* of this scan.
- ``timestamp``: seconds (float64), the scan's reference time.
- ``point_times``: optional (N,) float64, seconds *relative to* ``timestamp``
  (so a 10 Hz spinning sweep spans about 0..0.1 s, or -0.1..0 when the
  reference is the sweep end).
- ``gt_pose``: optional ``T_world_sensor`` (4x4 float64), see ``flowslam.geometry``.
- ``gt_flow``: optional (N,3) float64 scene flow in the Argoverse 2 convention:
  ``points + gt_flow`` is the same physical point at the next scan, expressed in
  the *next* sensor frame (static: ``T_{t+1,t} p - p``).
- ``gt_dynamic``: optional (N,) bool, the point moves in the world.
- ``gt_class``: optional (N,) int semantic class ids (dataset-specific).
- ``gt_instance``: optional (N,) int instance/track ids (-1 = none).
- ``extras``: reader-specific values; per-point arrays there are filtered with the
  points. Scene-flow labels every labelled reader provides: ``av2_category`` (N,) int
  (Argoverse 2 category index) and ``is_ground`` (N,) bool.

This is the data contract of the pipeline, kept beside the processing contracts
(``Frontend``/``Backend`` in :mod:`flowslam.interfaces`); the readers that implement
``Dataset`` live in ``flowslam.datasets``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError

log = logging.getLogger(__name__)

MIN_VALID_POINTS = 100
"""A scan with fewer usable points (finite, within ``max_coordinate_m``) than this is rejected as bad input."""

MAX_COORDINATE_M = 1000.0
"""Default plausible range (m): points with any ``|x|``, ``|y|`` or ``|z|`` beyond it are dropped
(``DatasetConfig.max_coordinate_m``)."""


@dataclass
class Frame:
    """One LiDAR scan with whatever ground truth its dataset carries (see module doc)."""

    index: int
    timestamp: float
    points: np.ndarray
    intensity: np.ndarray | None = None
    point_times: np.ndarray | None = None
    gt_pose: np.ndarray | None = None
    gt_flow: np.ndarray | None = None
    gt_dynamic: np.ndarray | None = None
    gt_class: np.ndarray | None = None
    gt_instance: np.ndarray | None = None
    source: str = ""
    """The file (or bag/topic) this scan came from, for messages."""
    extras: dict = field(default_factory=dict)
    """Reader-specific data; arrays of length N in here are per-point and filtered with the points."""

    def __len__(self) -> int:
        return len(self.points)

    @property
    def where(self) -> str:
        """The scan's file and index, for error messages ("FILE (frame 12)")."""
        return f"{self.source or 'frame'} (frame {self.index})"


_PER_POINT = ("intensity", "point_times", "gt_flow", "gt_dynamic", "gt_class", "gt_instance")


def _keep_points(frame: Frame, keep: np.ndarray) -> None:
    """Filter the points and every per-point array (fields and ``extras``) by the mask ``keep``."""
    n = len(keep)
    for name in _PER_POINT:
        arr = getattr(frame, name)
        if arr is not None:
            setattr(frame, name, np.asarray(arr)[keep])
    for key, arr in frame.extras.items():  # per-point arrays kept in extras
        if isinstance(arr, np.ndarray) and arr.ndim >= 1 and len(arr) == n:
            frame.extras[key] = arr[keep]
    frame.points = frame.points[keep]


def sanitize_frame(
    frame: Frame, min_points: int = MIN_VALID_POINTS, max_coordinate_m: float = MAX_COORDINATE_M
) -> Frame:
    """Drop unusable points and reject near-empty scans.

    A point is dropped when a coordinate is NaN/inf (each such scan logs the count) or
    its ``|x|``, ``|y|`` or ``|z|`` exceeds ``max_coordinate_m`` (metres, sensor frame; not
    logged here, see ``Dataset.sanitized``). The counts go to
    ``frame.extras["dropped_nonfinite"]`` and ``frame.extras["dropped_out_of_range"]``.
    Every per-point array is filtered with the same mask. Raises ``InputError`` naming
    ``frame.source`` when fewer than ``min_points`` usable points remain.
    """
    pts = np.asarray(frame.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(frame.source, f"points have shape {pts.shape}, expected (N, 3)")
    frame.points = pts
    n_nonfinite = n_far = 0
    # fast path: one reduction for clean scans (NaN makes the comparison False)
    if len(pts) and not np.abs(pts).max() <= max_coordinate_m:
        finite = geometry.finite_rows(pts)
        with np.errstate(invalid="ignore"):
            near = (np.abs(pts) <= max_coordinate_m).all(axis=1)
        n_nonfinite = int(len(pts) - finite.sum())
        n_far = int(finite.sum() - near.sum())
        if n_nonfinite:
            log.warning("%s: dropped %d points with NaN/inf coordinates", frame.source, n_nonfinite)
        _keep_points(frame, near)
    frame.extras["dropped_nonfinite"] = n_nonfinite
    frame.extras["dropped_out_of_range"] = n_far
    if len(frame.points) < min_points:
        far = f"; {n_far} dropped beyond {max_coordinate_m:g} m, see dataset.max_coordinate_m" if n_far else ""
        raise InputError(
            frame.source, f"only {len(frame.points)} valid points in this scan (need at least {min_points}{far})"
        )
    return frame


class Dataset:
    """Base class of all readers: a random-access sequence of ``Frame``.

    Subclasses set ``name``, ``path`` and implement ``__len__`` and ``_load(i)``;
    ``__getitem__`` sanitises every frame (``sanitized``). ``gt_poses`` is an optional
    (N,4,4) array of ``T_world_sensor`` and ``timestamps`` an (N,) array in seconds,
    strictly increasing (readers check it with ``flowslam.trajectory.checked_timestamps``).
    """

    name: str = "dataset"
    gt_poses: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    max_coordinate_m: float = MAX_COORDINATE_M
    """Plausible range of coordinates (m), set from ``DatasetConfig`` by ``open_dataset``."""
    _range_logged: bool = False

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def _load(self, index: int) -> Frame:  # pragma: no cover - abstract
        raise NotImplementedError

    def __getitem__(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        return self.sanitized(self._load(index))

    def sanitized(self, frame: Frame) -> Frame:
        """``sanitize_frame`` with this dataset's ``max_coordinate_m``; the first scan of the
        sequence that loses points beyond it logs one warning line with the count."""
        frame = sanitize_frame(frame, max_coordinate_m=self.max_coordinate_m)
        n_far = frame.extras["dropped_out_of_range"]
        if n_far and not self._range_logged:
            self._range_logged = True
            log.warning("%s: dropped %d points with a coordinate beyond %g m (dataset.max_coordinate_m); "
                        "later scans of this sequence count theirs in frame.extras['dropped_out_of_range']",
                        frame.source, n_far, self.max_coordinate_m)
        return frame

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def has_gt_poses(self) -> bool:
        return self.gt_poses is not None

    def describe(self) -> str:
        return f"{self.name} ({len(self)} frames) at {self.path}"


class ScanFileDataset(Dataset):
    """A dataset with one scan file per frame (KITTI, scan folders).

    Subclasses set ``scan_files`` (ordered), ``timestamps`` and optionally
    ``gt_poses``, and implement ``_read(path) -> (points (N,3), intensity (N,) or None)``.
    """

    scan_files: list[Path]

    def __len__(self) -> int:
        return len(self.scan_files)

    def _read(self, path: Path) -> tuple[np.ndarray, np.ndarray | None]:  # pragma: no cover
        raise NotImplementedError

    def _load(self, index: int) -> Frame:
        path = self.scan_files[index]
        points, intensity = self._read(path)
        return Frame(
            index=index,
            timestamp=float(self.timestamps[index]),
            points=points,
            intensity=intensity,
            gt_pose=None if self.gt_poses is None else self.gt_poses[index],
            source=str(path),
        )
