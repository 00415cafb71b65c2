"""KITTI odometry reader (``sequences/XX/velodyne/*.bin``, ``calib.txt``, ``times.txt``, ``poses/XX.txt``).

Frames: the *sensor frame* is the Velodyne frame. KITTI's GT poses are given for
camera 0 (``P_i = T_cam0(0)_cam0(i)``); with ``Tr = T_cam0_velo`` from ``calib.txt``
they become LiDAR poses ``T_world_velo_i = inv(Tr) @ P_i @ Tr``, where the world is
the Velodyne frame of scan 0 (so pose 0 is ~identity): :func:`cam0_poses_to_velo`, and
back to KITTI's convention (for ``trajectory_kitti.txt``) :func:`velo_poses_to_cam0`. Units: metres, seconds
(``times.txt``, relative to the sequence start, strictly increasing: else
``InputError``, or a logged repair with ``fix_times``). KITTI has no per-point time.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numba import njit

from flowslam import geometry
from flowslam.frame import ScanFileDataset
from flowslam.datasets.scan_files import DEFAULT_SCAN_PERIOD, natural_key, read_kitti_bin, read_times_file
from flowslam.errors import InputError
from flowslam.trajectory import read_trajectory

log = logging.getLogger(__name__)

def velo_poses_to_cam0(poses_velo: np.ndarray, T_cam0_velo: np.ndarray) -> np.ndarray:
    """LiDAR poses ``T_velo(0)_velo(k)`` (N,4,4) -> KITTI's camera-0 poses
    ``T_cam0(0)_cam0(k) = Tr @ T_velo(0)_velo(k) @ inv(Tr)`` (the convention of
    ``poses/XX.txt``; an identity first pose stays the identity). Metres.

    ``inv(Tr)`` is the exact matrix inverse, not the rigid one: ``calib.txt`` holds 7
    digits, so its rotation is orthonormal to ~1e-7 only, and this way the two
    conversions undo each other to rounding (``gt_kitti.txt`` = ``poses/XX.txt``)."""
    return T_cam0_velo @ np.asarray(poses_velo, dtype=np.float64) @ np.linalg.inv(T_cam0_velo)


def cam0_poses_to_velo(poses_cam0: np.ndarray, T_cam0_velo: np.ndarray) -> np.ndarray:
    """The inverse of :func:`velo_poses_to_cam0`: ``inv(Tr) @ P @ Tr`` (N,4,4)."""
    return np.linalg.inv(T_cam0_velo) @ np.asarray(poses_cam0, dtype=np.float64) @ T_cam0_velo


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Parse a KITTI ``calib.txt`` (``KEY: v1 v2 ...`` lines) into 3x4 matrices by key.

    ``Tr`` (= ``T_cam0_velo``) is required; ``P0``..``P3`` are optional.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read calibration file ({e.__class__.__name__})") from None
    calib: dict[str, np.ndarray] = {}
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        key, sep, vals = line.partition(":")
        if not sep:
            raise InputError(path, f"line {n} is not 'KEY: numbers'")
        try:
            nums = np.array(vals.split(), dtype=np.float64)
        except ValueError:
            raise InputError(path, f"line {n} ({key.strip()}) has non-numeric values") from None
        if nums.size != 12:
            raise InputError(path, f"line {n} ({key.strip()}) has {nums.size} numbers, expected 12 (3x4)")
        calib[key.strip()] = nums.reshape(3, 4)
    if "Tr" not in calib:
        raise InputError(path, f"no 'Tr:' (velodyne-to-camera) entry; found {sorted(calib) or 'nothing'}")
    return calib


def _find_sequence_dir(path: Path, sequence: str | int | None) -> tuple[Path, str]:
    """Resolve the user's path (root, ``sequences/XX`` or ``.../velodyne``) to a sequence folder."""
    seq = None if sequence is None else (f"{sequence:02d}" if isinstance(sequence, int) else str(sequence))
    if path.name == "velodyne" and path.is_dir():
        path = path.parent
    if (path / "velodyne").is_dir():
        if seq is not None and seq != path.name:
            raise InputError(path, f"is sequence {path.name!r} but sequence={seq!r} was requested")
        return path, path.name
    seq_root = path / "sequences"
    if not seq_root.is_dir():
        raise InputError(path, "not a KITTI odometry folder (expected sequences/XX/velodyne/ or velodyne/)")
    available = sorted(p.name for p in seq_root.iterdir() if (p / "velodyne").is_dir())
    if not available:
        raise InputError(seq_root, "holds no sequence folder with a velodyne/ subfolder")
    if seq is None:
        if len(available) > 1:
            raise InputError(path, f"holds several sequences ({', '.join(available)}); pick one with sequence=")
        seq = available[0]
    if seq not in available:
        raise InputError(path, f"has no sequence {seq!r} (available: {', '.join(available)})")
    return seq_root / seq, seq


KITTI_VERTICAL_CORRECTION_DEG = 0.205
"""Elevation error of KITTI's published Velodyne scans (deg), corrected at read time."""


def correct_elevation(points: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotate each point upwards by ``angle_rad`` in its own vertical plane.

    Range and azimuth stay; the elevation grows by ``angle_rad`` (the rotation
    about the horizontal axis ``p x z``). Points on the z axis (and rows with NaN in x or
    y) are left as they are. Compiled, one pass (``_corrected``); the same numbers as
    the NumPy form it replaced (``rho = hypot(x, y)``, ratio ``(rho cos - z sin) / rho``).
    """
    points = np.ascontiguousarray(points)
    return _corrected(points, float(np.cos(angle_rad)), float(np.sin(angle_rad)))


@njit(cache=True, nogil=True)
def _corrected(points, c, s):
    out = np.empty_like(points)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        rho = np.hypot(x, y)
        if rho > 0:
            ratio = (rho * c - z * s) / rho
            out[i, 0], out[i, 1], out[i, 2] = x * ratio, y * ratio, z * c + rho * s
        else:
            out[i, 0], out[i, 1], out[i, 2] = x, y, z
    return out


class KittiOdometry(ScanFileDataset):
    """One KITTI odometry sequence (see module doc for frames and units).

    Args:
        path: the dataset root holding ``sequences/`` (and ``poses/``), a sequence
            folder ``sequences/XX`` (poses looked up in ``../../poses/XX.txt``) or
            its ``velodyne`` folder.
        sequence: which sequence (``"00"`` or ``0``) when the root holds several.
        vertical_correction_deg: raise every beam's elevation by this angle
            (default 0.205 deg, KITTI's known HDL-64E intrinsic-calibration error, the
            correction KISS-ICP and IMLS-SLAM apply to KITTI scans); 0 reads the
            points exactly as stored.
        fix_times: repair ``times.txt`` values that do not increase strictly instead of raising.
    """

    name = "kitti"

    def __init__(
        self,
        path: str | Path,
        sequence: str | int | None = None,
        vertical_correction_deg: float = KITTI_VERTICAL_CORRECTION_DEG,
        fix_times: bool = False,
    ):
        super().__init__(path)
        self.vertical_correction_deg = float(vertical_correction_deg)
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        self.sequence_dir, self.sequence = _find_sequence_dir(self.path, sequence)
        velo = self.sequence_dir / "velodyne"
        self.scan_files = sorted(velo.glob("*.bin"), key=natural_key)
        if not self.scan_files:
            raise InputError(velo, "no .bin scans found")
        n = len(self.scan_files)
        times_path = self.sequence_dir / "times.txt"
        if times_path.exists():
            self.timestamps = read_times_file(times_path, expected=n, fix=fix_times)
        else:
            log.warning("%s: no times.txt, assuming %.1f s between scans", self.sequence_dir, DEFAULT_SCAN_PERIOD)
            self.timestamps = np.arange(n) * DEFAULT_SCAN_PERIOD
        calib_path = self.sequence_dir / "calib.txt"
        self.calib = read_kitti_calib(calib_path) if calib_path.exists() else None
        self.poses_path = self.sequence_dir.parent.parent / "poses" / f"{self.sequence}.txt"
        self.gt_poses = self._read_gt(calib_path) if self.poses_path.exists() else None

    @property
    def T_cam0_velo(self) -> np.ndarray | None:
        """The 4x4 ``Tr`` from ``calib.txt`` (LiDAR into camera 0), or None without calib."""
        return None if self.calib is None else geometry.make_T(self.calib["Tr"][:, :3], self.calib["Tr"][:, 3])

    def _read_gt(self, calib_path: Path) -> np.ndarray:
        traj = read_trajectory(self.poses_path, fmt="kitti")
        if len(traj) != len(self.scan_files):
            raise InputError(
                self.poses_path, f"has {len(traj)} poses but there are {len(self.scan_files)} scans"
            )
        if self.calib is None:
            raise InputError(calib_path, "missing; its Tr is needed to convert the camera-0 GT poses to LiDAR")
        return cam0_poses_to_velo(traj.poses, self.T_cam0_velo)

    def _read(self, path: Path) -> tuple[np.ndarray, np.ndarray | None]:
        points, intensity = read_kitti_bin(path)
        if self.vertical_correction_deg:
            points = correct_elevation(points, np.deg2rad(self.vertical_correction_deg))
        return points, intensity
