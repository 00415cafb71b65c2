"""Trajectories (stacks of ``T_world_sensor`` with timestamps) and their TUM / KITTI files.

File formats
------------
- KITTI: one pose per line, 12 numbers = the first three rows of the 4x4
  ``T_world_sensor`` in row-major order. No timestamps (index = frame).
- TUM: ``timestamp tx ty tz qx qy qz qw`` per line (seconds, metres, Hamilton
  quaternion with w last). Lines starting with ``#`` are comments.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError

__all__ = ["Trajectory", "read_trajectory", "write_tum", "write_kitti", "detect_format"]


@dataclass
class Trajectory:
    """Poses ``T_world_sensor`` (N,4,4) float64 and optional timestamps (N,) in seconds."""

    poses: np.ndarray
    timestamps: np.ndarray | None = None

    def __post_init__(self):
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if self.timestamps is not None:
            self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
            if len(self.timestamps) != len(self.poses):
                raise ValueError(
                    f"{len(self.timestamps)} timestamps for {len(self.poses)} poses"
                )

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def positions(self) -> np.ndarray:
        """(N,3) sensor positions in the world frame (m)."""
        return self.poses[:, :3, 3]

    def subset(self, idx) -> "Trajectory":
        return Trajectory(self.poses[idx], None if self.timestamps is None else self.timestamps[idx])

    def path_length(self) -> float:
        """Total travelled distance (m)."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def _load_table(path: Path) -> np.ndarray:
    if not path.exists():
        raise InputError(path, "file does not exist")
    if not path.is_file():
        raise InputError(path, "is not a file")
    try:
        rows = [
            line.replace(",", " ").split()
            for line in path.read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")
        ]
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read poses file ({e.__class__.__name__}: {e})") from None
    if not rows:
        raise InputError(path, "poses file holds no poses")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise InputError(path, f"poses file has rows of different lengths {sorted(widths)}")
    try:
        table = np.array(rows, dtype=np.float64)
    except ValueError:
        raise InputError(path, "poses file contains non-numeric values") from None
    if not np.isfinite(table).all():
        raise InputError(path, "poses file contains NaN or inf")
    return table


def detect_format(path: str | Path, table: np.ndarray | None = None) -> str:
    """``"kitti"`` for 12 columns, ``"tum"`` for 8; raises ``InputError`` otherwise.

    ``table`` is the file's already-parsed numbers, if the caller has them.
    """
    table = _load_table(Path(path)) if table is None else table
    ncol = table.shape[1]
    if ncol == 12:
        return "kitti"
    if ncol == 8:
        return "tum"
    raise InputError(path, f"poses file has {ncol} columns; expected 12 (KITTI) or 8 (TUM)")


def read_trajectory(path: str | Path, fmt: str | None = None) -> Trajectory:
    """Read a KITTI or TUM trajectory file (format guessed from the column count)."""
    path = Path(path)
    table = _load_table(path)
    fmt = fmt or detect_format(path, table)
    if fmt == "kitti":
        if table.shape[1] != 12:
            raise InputError(path, f"KITTI poses need 12 numbers per line, found {table.shape[1]}")
        poses = np.tile(np.eye(4), (len(table), 1, 1))
        poses[:, :3, :4] = table.reshape(-1, 3, 4)
        traj = Trajectory(poses)
    elif fmt == "tum":
        if table.shape[1] != 8:
            raise InputError(path, f"TUM poses need 8 numbers per line, found {table.shape[1]}")
        q = table[:, 4:8]
        norms = np.linalg.norm(q, axis=1)
        if np.any(norms < 1e-9):
            raise InputError(path, "TUM poses file has a zero quaternion")
        traj = Trajectory(geometry.from_quat_xyzw(q / norms[:, None], table[:, 1:4]), table[:, 0])
    else:
        raise InputError(path, f"unknown trajectory format {fmt!r} (use 'kitti' or 'tum')")
    bad = [i for i, T in enumerate(traj.poses) if not geometry.is_se3(T, tol=1e-4)]
    if bad:
        raise InputError(path, f"pose on line {bad[0] + 1} is not a rigid transform")
    return traj


def write_kitti(path: str | Path, traj: Trajectory | np.ndarray) -> None:
    """Write poses as KITTI lines (12 numbers, row-major 3x4)."""
    poses = traj.poses if isinstance(traj, Trajectory) else np.asarray(traj).reshape(-1, 4, 4)
    np.savetxt(path, poses[:, :3, :4].reshape(-1, 12), fmt="%.9e")


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a trajectory as TUM lines; frame indices stand in for missing timestamps."""
    stamps = traj.timestamps if traj.timestamps is not None else np.arange(len(traj), dtype=float)
    q = geometry.to_quat_xyzw(traj.poses).reshape(-1, 4)
    table = np.column_stack([stamps, traj.positions, q])
    np.savetxt(path, table, fmt=["%.9f"] + ["%.9e"] * 7, header="timestamp tx ty tz qx qy qz qw")
