"""Single-scan file readers shared by the KITTI and scan-folder readers.

Every reader returns ``(points, intensity)``: ``points`` (N,3) float64 in metres in
the sensor frame the file was written in (no transform is applied), ``intensity``
(N,) float64 in the file's own units (KITTI: reflectance 0..1) or ``None`` when the
file has none. Bad files raise ``InputError`` naming the file.

Also here: natural sorting of file names and the one-number-per-line ``times.txt``
reader (seconds).
"""

from __future__ import annotations

import math
import re
import tokenize
from pathlib import Path
from typing import Callable

import numpy as np

from flowslam.errors import InputError
from flowslam.trajectory import checked_timestamps

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


def read_file_bytes(path: Path) -> bytes:
    """The whole file; a missing or unreadable file is an ``InputError`` naming it."""
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
    raw = read_file_bytes(path)
    if len(raw) % 16:
        raise InputError(
            path, f"size {len(raw)} bytes is not a multiple of 16 (4 float32 per point; truncated .bin?)"
        )
    rec = np.frombuffer(raw, dtype=_KITTI_RECORD).reshape(-1, 4)
    return rec[:, :3].astype(np.float64), rec[:, 3].astype(np.float64)


def _real_numeric(dtype: np.dtype) -> bool:
    """A scalar integer or floating-point type (not bool, complex, string, object or sub-array)."""
    return dtype.kind in "iuf" and dtype.shape == ()


_NPY_ERRORS = (ValueError, OSError, EOFError, SyntaxError, TypeError, tokenize.TokenError)
"""What numpy raises on a corrupt ``.npy`` file (its header is a Python literal, parsed by ``ast``)."""


def _check_npy_size(path: Path) -> None:
    """``InputError`` unless the data after the ``.npy`` header are exactly what it declares.

    Checked before ``np.load``, which ignores extra bytes and would first allocate the
    declared size (a corrupt shape can ask for terabytes).
    """
    from numpy.lib import format as npy

    with open(path, "rb") as f:
        if f.read(6) != npy.MAGIC_PREFIX:
            raise InputError(path, "not a readable .npy array (no NUMPY magic at its start; an .npz archive?)")
        f.seek(0)
        version = npy.read_magic(f)
        read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, _fortran, dtype = read_header(f)
        have = path.stat().st_size - f.tell()
    need = math.prod(shape) * dtype.itemsize
    if dtype.hasobject:
        raise InputError(path, f"holds Python objects (dtype {dtype}), not numbers")
    if have != need:
        raise InputError(path, f"holds {have} data bytes but its header declares shape {shape} of {dtype} = "
                               f"{need} bytes{' (truncated .npy?)' if have < need else ''}")


def read_npy_scan(path: str | Path) -> ScanArrays:
    """Read a ``.npy`` scan: a numeric (N,3) ``x y z`` or (N,4+) ``x y z intensity ...`` array,
    or a structured array with fields ``x``, ``y``, ``z`` (and optionally ``intensity``).

    Integer or floating-point values only; anything else (an ``.npz`` archive, object,
    complex or string data, another shape) raises ``InputError``.
    """
    path = Path(path)
    try:
        _check_npy_size(path)
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except _NPY_ERRORS as e:
        raise InputError(path, f"not a readable .npy array ({e.__class__.__name__}: {e})") from None
    if arr.dtype.names:
        missing = [k for k in "xyz" if k not in arr.dtype.names]
        if missing:
            raise InputError(path, f"structured array lacks fields {missing} (has {list(arr.dtype.names)})")
        bad = [k for k in ("x", "y", "z", "intensity") if k in arr.dtype.names and not _real_numeric(arr.dtype[k])]
        if bad:
            raise InputError(path, f"structured array field {bad[0]!r} has type {arr.dtype[bad[0]]}, not a number")
        arr = arr.reshape(-1)
        pts = np.column_stack([arr[k].astype(np.float64) for k in "xyz"]).reshape(-1, 3)
        inten = arr["intensity"].astype(np.float64) if "intensity" in arr.dtype.names else None
        return pts, inten
    if arr.ndim != 2 or arr.shape[1] < 3 or not _real_numeric(arr.dtype):
        raise InputError(
            path, f"array has shape {arr.shape} and dtype {arr.dtype}; expected numeric (N,3) or (N,4+)"
        )
    return arr[:, :3].astype(np.float64), (arr[:, 3].astype(np.float64) if arr.shape[1] > 3 else None)


def read_ply(path: str | Path) -> ScanArrays:
    """Read a ``.ply`` point cloud (``flowslam.datasets.ply``; keeps an ``intensity`` property)."""
    from flowslam.datasets.ply import read_ply as _read

    return _read(Path(path))


def read_pcd_scan(path: str | Path) -> ScanArrays:
    """Read a ``.pcd`` scan (``DATA ascii``, ``binary`` or ``binary_compressed``; ``flowslam.datasets.pcd``)."""
    from flowslam.datasets.pcd import read_pcd

    return read_pcd(Path(path))


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


def read_times_file(path: str | Path, expected: int | None = None, fix: bool = False) -> np.ndarray:
    """Read a ``times.txt``: one timestamp per line in seconds -> (N,) float64.

    Raises ``InputError`` for unreadable, non-numeric or non-finite content, when
    ``expected`` is given and the line count differs, or when the times do not
    increase strictly (repaired instead with ``fix``: ``checked_timestamps``).
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
    return checked_timestamps(times, path, fix=fix)
