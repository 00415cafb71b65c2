"""A small reader for PCL's ``.pcd`` files (``DATA ascii`` and ``DATA binary``).

The header (``FIELDS``/``SIZE``/``TYPE``/``COUNT``/``WIDTH``/``HEIGHT``/``POINTS``/``DATA``)
defines the record layout; nothing is assumed about field order, padding fields
(PCL writes ``_``) or extra fields. ``x y z`` are required; the first of
``INTENSITY_FIELDS`` present becomes the intensity. Coordinates are returned in
the file's frame (metres); the ``VIEWPOINT`` entry is not applied.
``DATA binary_compressed`` (LZF) is not parsed here: ``read_pcd`` returns ``None``
and the caller hands the file to Open3D.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowslam.errors import InputError

INTENSITY_FIELDS = ("intensity", "i", "reflectance")
"""Field names accepted as intensity (first match wins), shared with the PointCloud2 decoder."""

_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


@dataclass
class PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    points: int
    data: str
    data_offset: int
    """Byte offset of the first data byte (just after the ``DATA`` line)."""


def parse_pcd_header(raw: bytes, path: Path) -> PcdHeader:
    """Parse the ASCII header at the start of ``raw``; ``InputError`` when malformed."""
    entries: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > 65536:
            raise InputError(path, "no 'DATA' line found in the PCD header (not a .pcd file?)")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        entries[key.upper()] = vals
        if key.upper() == "DATA":
            break
    try:
        fields = entries.get("FIELDS") or entries["COLUMNS"]
        n = len(fields)
        sizes = [int(s) for s in entries.get("SIZE", ["4"] * n)]
        types = [t.upper() for t in entries.get("TYPE", ["F"] * n)]
        counts = [int(c) for c in entries.get("COUNT", ["1"] * n)]
        width = int(entries["WIDTH"][0])
        height = int(entries.get("HEIGHT", ["1"])[0])
        points = int(entries.get("POINTS", [str(width * height)])[0])
        data = entries["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as e:
        raise InputError(path, f"malformed PCD header ({e.__class__.__name__}: {e})") from None
    if not (len(sizes) == len(types) == len(counts) == n):
        raise InputError(path, "PCD header FIELDS/SIZE/TYPE/COUNT have different lengths")
    bad = [(t, s) for t, s in zip(types, sizes) if (t, s) not in _TYPES]
    if bad:
        raise InputError(path, f"unsupported PCD TYPE/SIZE {bad[0][0]}{bad[0][1]}")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise InputError(path, f"unsupported PCD DATA {data!r}")
    return PcdHeader(fields, sizes, types, counts, points, data, pos)


def _pick(names: list[str], wanted: tuple[str, ...]) -> str | None:
    return next((w for w in wanted if w in names), None)


def read_pcd(path: str | Path) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Read a .pcd file -> ``(points (N,3) float64, intensity (N,) float64 | None)``.

    Returns ``None`` for ``binary_compressed`` data (see module doc).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except OSError as e:
        raise InputError(path, f"cannot read file ({e.strerror or e})") from None
    hdr = parse_pcd_header(raw, path)
    missing = [k for k in "xyz" if k not in hdr.fields]
    if missing:
        raise InputError(path, f"PCD has no field(s) {missing} (fields: {hdr.fields})")
    inten_name = _pick(hdr.fields, INTENSITY_FIELDS)
    if hdr.data == "binary_compressed":
        return None
    if hdr.data == "binary":
        cols = _binary_columns(raw, hdr, path)
    else:
        cols = _ascii_columns(raw, hdr, path)
    pts = np.column_stack([cols[k] for k in "xyz"]).astype(np.float64)
    inten = cols[inten_name].astype(np.float64) if inten_name else None
    return pts, inten


def _binary_columns(raw: bytes, hdr: PcdHeader, path: Path) -> dict[str, np.ndarray]:
    names, formats, offsets, off = [], [], [], 0
    for k, (f, s, t, c) in enumerate(zip(hdr.fields, hdr.sizes, hdr.types, hdr.counts)):
        names.append(f if f not in names else f"{f}__{k}")  # PCL repeats '_' for padding
        formats.append(("<" + _TYPES[(t, s)], (c,)) if c > 1 else "<" + _TYPES[(t, s)])
        offsets.append(off)
        off += s * c
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})
    need = hdr.points * dt.itemsize
    have = len(raw) - hdr.data_offset
    if have < need:
        raise InputError(path, f"binary data has {have} bytes but the header promises {hdr.points} points x "
                               f"{dt.itemsize} bytes = {need} (truncated .pcd?)")
    rec = np.frombuffer(raw, dtype=dt, count=hdr.points, offset=hdr.data_offset)
    return {n: (rec[n][:, 0] if rec[n].ndim > 1 else rec[n]) for n in hdr.fields if n in dt.names}


def _ascii_columns(raw: bytes, hdr: PcdHeader, path: Path) -> dict[str, np.ndarray]:
    width = sum(hdr.counts)
    try:
        values = np.array(raw[hdr.data_offset:].split(), dtype=np.float64)
    except ValueError:
        raise InputError(path, "ASCII data contains non-numeric values") from None
    if values.size != hdr.points * width:
        raise InputError(path, f"ASCII data has {values.size} numbers, expected {hdr.points} points x {width} "
                               f"values (truncated .pcd?)")
    table = values.reshape(hdr.points, width)
    starts = np.cumsum([0] + hdr.counts[:-1])
    cols: dict[str, np.ndarray] = {}
    for name, start in zip(hdr.fields, starts):
        cols.setdefault(name, table[:, start])
    return cols
