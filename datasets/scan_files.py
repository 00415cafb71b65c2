"""Single-scan file readers shared by the KITTI and scan-folder readers.

Every reader returns ``(points, intensity)``: ``points`` (N,3) float64 in metres in
the sensor frame the file was written in (no transform is applied), ``intensity``
(N,) float64 in the file's own units (KITTI: reflectance 0..1) or ``None`` when the
file has none. Bad files raise ``InputError`` naming the file.

Also here: natural sorting of file names and the one-number-per-line ``times.txt``
reader (seconds).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam.errors import InputError

ScanArrays = tuple[np.ndarray, "np.ndarray | None"]

SCAN_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
"""File types ``read_scan`` understands (case-insensitive)."""

DEFAULT_SCAN_PERIOD = 0.1
"""Seconds between scans assumed when a dataset gives no timestamps (a 10 Hz spinning LiDAR)."""

_KITTI_RECORD = np.dtype("<f4")  # x y z intensity, little-endian float32


def natural_key(path: str | Path) -> list:
    """Sort key that orders ``scan2`` before ``scan10`` (digit runs compare as numbers)."""
    name = Path(path).name
    return [(0, int(tok), "") if tok.isdigit() else (1, 0, tok.lower()) for tok in re.split(r"(\d+)", name) if tok]


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except OSError as e:
        raise InputError(path, f"cannot read file ({e.strerror or e})") from None


def read_kitti_bin(path: str | Path) -> ScanArrays:
    """Read a KITTI Velodyne ``.bin`` scan: little-endian float32 records ``x y z intensity``.

    Points are in the LiDAR frame (m); intensity is KITTI reflectance (0..1).
    A size that is not a multiple of 16 bytes raises ``InputError`` (truncated file).
    """
    path = Path(path)
    raw = _read_bytes(path)
    if len(raw) % 16:
        raise InputError(
            path, f"size {len(raw)} bytes is not a multiple of 16 (4 float32 per point; truncated .bin?)"
        )
    rec = np.frombuffer(raw, dtype=_KITTI_RECORD).reshape(-1, 4)
    return rec[:, :3].astype(np.float64), rec[:, 3].astype(np.float64)


def read_npy_scan(path: str | Path) -> ScanArrays:
    """Read a ``.npy`` scan: a numeric (N,3) ``x y z`` or (N,4+) ``x y z intensity ...`` array,
    or a structured array with fields ``x``, ``y``, ``z`` (and optionally ``intensity``)."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except (ValueError, OSError, EOFError) as e:
        raise InputError(path, f"not a readable .npy array ({e})") from None
    if arr.dtype.names:
        missing = [k for k in "xyz" if k not in arr.dtype.names]
        if missing:
            raise InputError(path, f"structured array lacks fields {missing} (has {list(arr.dtype.names)})")
        arr = arr.reshape(-1)
        pts = np.column_stack([arr[k].astype(np.float64) for k in "xyz"])
        inten = arr["intensity"].astype(np.float64) if "intensity" in arr.dtype.names else None
        return pts, inten
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise InputError(
            path, f"array has shape {arr.shape} and dtype {arr.dtype}; expected numeric (N,3) or (N,4+)"
        )
    return arr[:, :3].astype(np.float64), (arr[:, 3].astype(np.float64) if arr.shape[1] > 3 else None)


def read_ply(path: str | Path) -> ScanArrays:
    """Read a ``.ply`` point cloud with Open3D's tensor IO (keeps an ``intensity`` property)."""
    return _read_open3d(Path(path))


def _read_open3d(path: Path) -> ScanArrays:
    import open3d as o3d  # heavy: imported only when such a file is read

    if not path.is_file():
        raise InputError(path, "file does not exist")
    pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or len(pc.point.positions) == 0:
        raise InputError(path, "Open3D read no points from this file (corrupt or unsupported?)")
    pts = pc.point.positions.numpy().astype(np.float64)
    inten = pc.point.intensity.numpy().reshape(-1).astype(np.float64) if "intensity" in pc.point else None
    return pts, inten


def read_pcd_scan(path: str | Path) -> ScanArrays:
    """Read a ``.pcd`` scan (ASCII or binary by our parser; binary_compressed via Open3D)."""
    from flowslam.datasets.pcd import read_pcd

    path = Path(path)
    cloud = read_pcd(path)
    if cloud is None:  # binary_compressed: LZF, left to Open3D
        return _read_open3d(path)
    return cloud


_READERS: dict[str, Callable[[Path], ScanArrays]] = {
    ".bin": read_kitti_bin,
    ".npy": read_npy_scan,
    ".pcd": read_pcd_scan,
    ".ply": read_ply,
}


def read_scan(path: str | Path) -> ScanArrays:
    """Read one scan file of any type in ``SCAN_SUFFIXES`` (chosen by suffix)."""
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(path, f"unsupported scan file type {path.suffix!r} (use {'/'.join(SCAN_SUFFIXES)})")
    return reader(path)


def read_times_file(path: str | Path, expected: int | None = None) -> np.ndarray:
    """Read a ``times.txt``: one timestamp per line in seconds -> (N,) float64.

    Raises ``InputError`` for unreadable or non-numeric content, or when
    ``expected`` is given and the line count differs.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
        tokens = [ln.split()[0] for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
        times = np.array(tokens, dtype=np.float64)
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read times file ({e.__class__.__name__})") from None
    except ValueError:
        raise InputError(path, "times file contains non-numeric values") from None
    if not np.isfinite(times).all():
        raise InputError(path, "times file contains NaN or inf")
    if expected is not None and len(times) != expected:
        raise InputError(path, f"has {len(times)} timestamps but there are {expected} scans")
    return times
