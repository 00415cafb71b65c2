"""A generic folder of scan files (``.bin`` KITTI float32 x4, ``.pcd``, ``.ply``, ``.npy``).

Frames: each file's points are taken as they are, in its own *sensor frame*
(metres). Scans are ordered by natural sort of the file names (``2`` before ``10``).

Ground truth poses (``T_world_sensor``, one per scan, in scan order) come from the
``poses=`` file, else the first of ``POSE_FILE_NAMES`` found in the folder; KITTI
(12 columns) or TUM (8 columns) via ``flowslam.trajectory.read_trajectory``.

Timestamps (seconds), first rule that applies:
1. the TUM poses file's stamps;
2. ``times.txt`` in the folder (one number per line);
3. numeric file stems: values > 1e12 are nanoseconds, others seconds; but stems
   that are consecutive integers below 1e6 (``000000``, ``000001``, ...) are
   frame indices, not times, and fall through to rule 4;
4. 0.1 s per frame (logged).

The times must increase strictly: otherwise ``InputError`` naming the file they come
from (the poses file, ``times.txt``, or the folder and the two scan files), unless
``fix_times`` repairs them (``flowslam.trajectory.checked_timestamps``, logged).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from flowslam.frame import ScanFileDataset
from flowslam.datasets.scan_files import (
    DEFAULT_SCAN_PERIOD,
    SCAN_SUFFIXES,
    natural_key,
    read_scan,
    read_times_file,
)
from flowslam.errors import InputError
from flowslam.trajectory import checked_timestamps, read_trajectory

log = logging.getLogger(__name__)

POSE_FILE_NAMES = ("poses.txt", "poses_kitti.txt", "poses_tum.txt", "groundtruth.txt")
"""Pose files discovered automatically inside the scan folder, in this order."""


def list_scan_files(folder: Path) -> list[Path]:
    """Scan files of the supported types in ``folder``, naturally sorted."""
    return sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES), key=natural_key
    )


def timestamps_from_stems(files: list[Path]) -> np.ndarray | None:
    """Seconds from numeric file stems (rule 3 of the module doc), or None."""
    try:
        values = np.array([float(p.stem) for p in files])
    except ValueError:
        return None
    if not np.isfinite(values).all():
        return None
    integers = bool(np.all(values == np.round(values))) and values[0] < 1e6
    if integers and (len(values) == 1 or np.all(np.diff(values) == 1)):
        return None  # frame indices 000000, 000001, ...
    if np.all(values > 1e12):
        return np.array([int(p.stem.split(".")[0]) for p in files], dtype=np.int64) * 1e-9
    return values


class ScanFolder(ScanFileDataset):
    """A folder of scan files with optional GT poses (see module doc).

    Args:
        path: the folder.
        poses: a KITTI or TUM poses file with one pose per scan (overrides discovery).
        fix_times: repair timestamps that do not increase strictly instead of raising.
    """

    name = "folder"

    def __init__(self, path: str | Path, poses: str | Path | None = None, fix_times: bool = False):
        super().__init__(path)
        self.fix_times = fix_times
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        if not self.path.is_dir():
            raise InputError(self.path, "is not a folder of scans")
        self.scan_files = list_scan_files(self.path)
        if not self.scan_files:
            raise InputError(self.path, "no scans (.bin/.pcd/.ply/.npy) found")
        n = len(self.scan_files)
        self.poses_path = Path(poses) if poses is not None else self._discover_poses()
        tum_times = None
        if self.poses_path is not None:
            traj = read_trajectory(self.poses_path, fix_times=fix_times)
            if len(traj) != n:
                raise InputError(self.poses_path, f"has {len(traj)} poses but the folder has {n} scans")
            self.gt_poses = traj.poses
            tum_times = traj.timestamps
        self.timestamps = self._timestamps(tum_times)

    def _discover_poses(self) -> Path | None:
        return next((self.path / f for f in POSE_FILE_NAMES if (self.path / f).is_file()), None)

    def _timestamps(self, tum_times: np.ndarray | None) -> np.ndarray:
        if tum_times is not None:
            return tum_times
        times_path = self.path / "times.txt"
        if times_path.is_file():
            return read_times_file(times_path, expected=len(self.scan_files), fix=self.fix_times)
        stems = timestamps_from_stems(self.scan_files)
        if stems is not None:
            names = [p.name for p in self.scan_files]
            return checked_timestamps(stems, self.path, fix=self.fix_times, what="times from the file names (s)",
                                      names=names)
        log.warning("%s: no timestamps found, assuming %.1f s between scans", self.path, DEFAULT_SCAN_PERIOD)
        return np.arange(len(self.scan_files)) * DEFAULT_SCAN_PERIOD

    def _read(self, path: Path) -> tuple[np.ndarray, np.ndarray | None]:
        points, intensity = read_scan(path)
        return points, intensity
