"""Trajectories (stacks of ``T_world_sensor`` with timestamps) and their TUM / KITTI files.

File formats
------------
- KITTI: one pose per line, 12 numbers = the first three rows of the 4x4
  ``T_world_sensor`` in row-major order. No timestamps (index = frame).
- TUM: ``timestamp tx ty tz qx qy qz qw`` per line (seconds, metres, Hamilton
  quaternion with w last). Lines starting with ``#`` are comments. Timestamps must
  increase strictly (``checked_timestamps``).

Every malformed file raises ``InputError`` naming the file and the problem in one line.

Also here: ``checked_timestamps``, the one check (and optional repair) of "timestamps
increase strictly" that every dataset reader applies to its scan times.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from flowslam import geometry
from flowslam.errors import InputError

__all__ = ["Trajectory", "read_trajectory", "write_tum", "write_kitti", "detect_format", "checked_timestamps",
           "unit_quaternions"]

log = logging.getLogger(__name__)

FIX_TIMES_HINT = "--fix-times (dataset.fix_times: true) repairs them"
"""What the timestamp error of a dataset reader suggests."""


def _show(value) -> str:
    return str(int(value)) if np.issubdtype(np.asarray(value).dtype, np.integer) else repr(float(value))


def checked_timestamps(
    times: np.ndarray,
    where: str | Path,
    *,
    fix: bool = False,
    what: str = "timestamps (s)",
    names: Sequence[str] | None = None,
    hint: str = FIX_TIMES_HINT,
) -> np.ndarray:
    """``times`` (N,) if they increase strictly, else ``InputError`` or (``fix``) a repaired copy.

    The error names ``where``, the first offending index ``i`` and the values
    ``times[i-1]``, ``times[i]`` (and ``names[i-1]``, ``names[i]`` when given, e.g. the
    scan files the times come from); ``hint`` is appended. With ``fix`` each time that is
    not after the (repaired) previous one becomes the previous + the median positive
    interval, or the midpoint to the next good time when that is closer (so one bad
    time does not shift all later ones); one warning line says how many changed.
    Works in the array's own units and dtype (seconds as float, or integer
    nanoseconds, which float64 cannot hold exactly).
    """
    times = np.asarray(times)
    diffs = np.diff(times)
    bad = np.flatnonzero(~(diffs > 0))  # NaN differences count as bad too
    if bad.size == 0:
        return times
    i = int(bad[0]) + 1
    files = f" ({names[i - 1]}, {names[i]})" if names is not None else ""
    problem = (f"{what} must increase strictly: #{i} = {_show(times[i])} is not after "
               f"#{i - 1} = {_show(times[i - 1])}{files}")
    positive = diffs[diffs > 0]
    if not fix or positive.size == 0:
        reason = "; cannot repair: no positive interval" if fix else (f"; {hint}" if hint else "")
        raise InputError(where, problem + reason)
    step = np.median(positive).astype(times.dtype) if times.dtype.kind in "iu" else np.median(positive)
    fixed = _repair_times(times, step)
    changed = int(np.count_nonzero(fixed != times))
    log.warning("%s: %s; fix_times replaced %d of %d by the previous + the median interval %s "
                "(or the midpoint to the next good time)", where, problem, changed, len(times),
                _show(step) if times.dtype.kind in "iu" else f"{step:.6g}")
    return fixed


def _repair_times(times: np.ndarray, step) -> np.ndarray:
    """``checked_timestamps``'s repair: one forward pass, the next good time found by a moving index."""
    fixed = times.copy()
    n, j = len(times), 1
    for k in range(1, n):
        prev = fixed[k - 1]
        if fixed[k] > prev:
            continue
        j = max(j, k + 1)
        while j < n and not times[j] > prev:
            j += 1
        value = prev + step
        if j < n:
            mid = prev + (times[j] - prev) // 2 if times.dtype.kind in "iu" else prev + (times[j] - prev) / 2
            value = min(value, mid) if mid > prev else value
        fixed[k] = value
    return fixed


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


def read_trajectory(path: str | Path, fmt: str | None = None, *, fix_times: bool = False) -> Trajectory:
    """Read a KITTI or TUM trajectory file (format guessed from the column count).

    Poses are ``T_world_sensor`` (metres), TUM timestamps seconds. Raises ``InputError``
    (one line naming the file) for a missing/unreadable/empty file, rows of different
    lengths, non-numeric or non-finite values, a wrong column count, a zero quaternion,
    a pose that is not a rigid transform, or TUM timestamps that do not increase
    strictly (repaired instead with ``fix_times``, see ``checked_timestamps``).
    """
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
        stamps = checked_timestamps(table[:, 0], path, fix=fix_times, hint="")
        traj = Trajectory(geometry.from_quat_xyzw(unit_quaternions(table[:, 4:8], path, "TUM poses file"), table[:, 1:4]), stamps)
    else:
        raise InputError(path, f"unknown trajectory format {fmt!r} (use 'kitti' or 'tum')")
    bad = [i for i, T in enumerate(traj.poses) if not geometry.is_se3(T, tol=1e-4)]
    if bad:
        raise InputError(path, f"pose on line {bad[0] + 1} is not a rigid transform")
    return traj


def unit_quaternions(q: np.ndarray, where: str | Path, what: str = "poses file") -> np.ndarray:
    """Normalised (N,4) quaternions (any component order). Each is scaled by its largest
    component first, so that huge values (1e300) do not overflow to a zero quaternion;
    ``InputError`` naming ``where`` for a zero or non-finite one."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    scale = np.abs(q).max(axis=1) if len(q) else np.zeros(0)
    bad = ~(scale >= 1e-9) | ~np.isfinite(scale)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(where, f"{what} has a zero quaternion (or a non-finite one) on pose {k}")
    q = q / scale[:, None]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


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
