"""A reader for PCL's ``.pcd`` files (``DATA ascii``, ``binary`` and ``binary_compressed``).

The header (``FIELDS``/``SIZE``/``TYPE``/``COUNT``/``WIDTH``/``HEIGHT``/``POINTS``/``DATA``)
defines the record layout; nothing is assumed about field order, padding fields
(PCL writes ``_``) or extra fields. ``x y z`` are required; the first of
``INTENSITY_FIELDS`` present becomes the intensity; a field with ``COUNT`` > 1
contributes its first element. Coordinates are returned in the file's frame (metres);
the ``VIEWPOINT`` entry is not applied.

Point count: ``WIDTH`` x ``HEIGHT`` and the data are trusted, ``POINTS`` is not (it is
redundant, and a wrong one must not silently drop most of a scan): when it disagrees,
one warning line names the file and both numbers and every point is read. Data that
hold fewer (truncated) or more points than ``WIDTH`` x ``HEIGHT`` raise ``InputError``.

``binary_compressed`` data (PCL's layout: uint32 compressed size, uint32 uncompressed
size, then LZF-compressed bytes holding each field's values for all points in turn)
are decompressed here, so that a corrupt or truncated file is an ``InputError``.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowslam.datasets.scan_files import read_file_bytes
from flowslam.errors import InputError

log = logging.getLogger(__name__)

INTENSITY_FIELDS = ("intensity", "i", "reflectance")
"""Field names accepted as intensity (first match wins), shared with the PointCloud2 and PLY readers."""

_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}

_MAX_HEADER = 65536
"""Bytes searched for the ``DATA`` line."""


@dataclass
class PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    points: int
    """The ``POINTS`` entry (``width * height`` when absent); not trusted, see module doc."""
    data: str
    data_offset: int
    """Byte offset of the first data byte (just after the ``DATA`` line)."""

    @property
    def n_points(self) -> int:
        """Points in the cloud: ``WIDTH`` x ``HEIGHT``."""
        return self.width * self.height

    @property
    def point_size(self) -> int:
        """Bytes per point (every field's ``SIZE`` x ``COUNT``)."""
        return sum(s * c for s, c in zip(self.sizes, self.counts))


def _header_entries(raw: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """``KEY -> values`` of the header lines up to ``DATA``, and the offset just after it."""
    entries: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > _MAX_HEADER:
            raise InputError(path, "no 'DATA' line found in the PCD header (not a .pcd file?)")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        entries[key.upper()] = vals
        if key.upper() == "DATA":
            return entries, pos


def parse_pcd_header(raw: bytes, path: Path) -> PcdHeader:
    """Parse the ASCII header at the start of ``raw``; ``InputError`` when malformed."""
    entries, pos = _header_entries(raw, path)
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
    if min(counts) < 1:
        raise InputError(path, f"PCD header COUNT {min(counts)} (must be >= 1)")
    if width < 0 or height < 0:
        raise InputError(path, f"PCD header WIDTH {width} / HEIGHT {height} (must be >= 0)")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise InputError(path, f"unsupported PCD DATA {data!r}")
    return PcdHeader(fields, sizes, types, counts, width, height, points, data, pos)


def _pick(names: list[str], wanted: tuple[str, ...]) -> str | None:
    return next((w for w in wanted if w in names), None)


def read_pcd(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a .pcd file -> ``(points (N,3) float64 m, intensity (N,) float64 | None)``.

    ``N`` = ``WIDTH`` x ``HEIGHT`` (module doc); ``InputError`` for a malformed,
    truncated or inconsistent file.
    """
    path = Path(path)
    raw = read_file_bytes(path)
    hdr = parse_pcd_header(raw, path)
    missing = [k for k in "xyz" if k not in hdr.fields]
    if missing:
        raise InputError(path, f"PCD has no field(s) {missing} (fields: {hdr.fields})")
    cols = _COLUMNS[hdr.data](raw, hdr, path)
    if hdr.points != hdr.n_points:
        log.warning("%s: PCD header says POINTS %d but WIDTH x HEIGHT and the data hold %d points; "
                    "reading all %d", path, hdr.points, hdr.n_points, hdr.n_points)
    inten_name = _pick(hdr.fields, INTENSITY_FIELDS)
    pts = np.column_stack([cols[k] for k in "xyz"]).astype(np.float64).reshape(-1, 3)
    inten = cols[inten_name].astype(np.float64) if inten_name else None
    return pts, inten


def _check_size(have: int, hdr: PcdHeader, path: Path, unit: int, what: str, noun: str = "bytes",
                slack: int = 0) -> None:
    """``InputError`` unless ``have`` (bytes or numbers) is ``WIDTH x HEIGHT`` points of ``unit``
    each, plus at most ``slack`` (e.g. a trailing newline after binary data)."""
    need = hdr.n_points * unit
    if have < need:
        raise InputError(path, f"{what} has {have} {noun} but WIDTH x HEIGHT = {hdr.n_points} points x {unit} "
                               f"= {need} (truncated .pcd?)")
    if have > need + slack:
        raise InputError(path, f"{what} has {have} {noun}, more than WIDTH x HEIGHT = {hdr.n_points} points x "
                               f"{unit} = {need} (POINTS {hdr.points}): the header does not describe the data")


def _record_dtype(hdr: PcdHeader) -> np.dtype:
    """The packed little-endian record of one point (``binary`` data)."""
    names, formats, offsets, off = [], [], [], 0
    for k, (f, s, t, c) in enumerate(zip(hdr.fields, hdr.sizes, hdr.types, hdr.counts)):
        names.append(f if f not in names else f"{f}__{k}")  # PCL repeats '_' for padding
        formats.append(("<" + _TYPES[(t, s)], (c,)) if c > 1 else "<" + _TYPES[(t, s)])
        offsets.append(off)
        off += s * c
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})


def _binary_columns(raw: bytes, hdr: PcdHeader, path: Path) -> dict[str, np.ndarray]:
    dt = _record_dtype(hdr)
    _check_size(len(raw) - hdr.data_offset, hdr, path, dt.itemsize, "binary data", slack=dt.itemsize - 1)
    rec = np.frombuffer(raw, dtype=dt, count=hdr.n_points, offset=hdr.data_offset)
    return {n: (rec[n][:, 0] if rec[n].ndim > 1 else rec[n]) for n in hdr.fields if n in dt.names}


def _ascii_columns(raw: bytes, hdr: PcdHeader, path: Path) -> dict[str, np.ndarray]:
    width = sum(hdr.counts)
    try:
        values = np.array(raw[hdr.data_offset:].split(), dtype=np.float64)
    except ValueError:
        raise InputError(path, "ASCII data contains non-numeric values") from None
    _check_size(values.size, hdr, path, width, "ASCII data", noun="numbers")
    table = values.reshape(hdr.n_points, width)
    starts = np.cumsum([0] + hdr.counts[:-1])
    cols: dict[str, np.ndarray] = {}
    for name, start in zip(hdr.fields, starts):
        cols.setdefault(name, table[:, start])
    return cols


def _compressed_columns(raw: bytes, hdr: PcdHeader, path: Path) -> dict[str, np.ndarray]:
    off = hdr.data_offset
    if len(raw) < off + 8:
        raise InputError(path, "binary_compressed data ends before its sizes (truncated .pcd?)")
    packed, unpacked = struct.unpack_from("<II", raw, off)
    body = raw[off + 8:off + 8 + packed]
    if len(body) < packed:
        raise InputError(path, f"binary_compressed data has {len(body)} of its {packed} bytes (truncated .pcd?)")
    _check_size(unpacked, hdr, path, hdr.point_size, "binary_compressed data (unpacked)")
    data = lzf_decompress(body, unpacked, path)
    cols: dict[str, np.ndarray] = {}
    start, n = 0, hdr.n_points
    for f, s, t, c in zip(hdr.fields, hdr.sizes, hdr.types, hdr.counts):  # field after field, all points each
        block = np.frombuffer(data, dtype="<" + _TYPES[(t, s)], count=n * c, offset=start)
        cols.setdefault(f, block.reshape(n, c)[:, 0])
        start += n * s * c
    return cols


def lzf_decompress(src: bytes, size: int, path: Path) -> bytes:
    """Decompress LZF data (liblzf's format, used by PCL) that must unpack to exactly ``size`` bytes.

    ``InputError`` naming ``path`` for corrupt or truncated data.
    """
    out = bytearray()
    ip, end = 0, len(src)

    def corrupt(why: str) -> InputError:
        return InputError(path, f"binary_compressed data is corrupt ({why} at byte {ip})")

    while ip < end:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            stop = ip + ctrl + 1
            if stop > end:
                raise corrupt("literal run past the end")
            out += src[ip:stop]
            ip = stop
        else:  # a back reference: length (3 bits, + a byte if all set), distance (5 + 8 bits)
            length = ctrl >> 5
            if length == 7:
                if ip >= end:
                    raise corrupt("back reference cut short")
                length += src[ip]
                ip += 1
            if ip >= end:
                raise corrupt("back reference cut short")
            back = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - back
            if start < 0:
                raise corrupt("back reference before the start")
            if back >= length:
                out += out[start:start + length]
            else:  # overlapping copy: the last `back` bytes repeat
                out += (out[start:] * (length // back + 1))[:length]
        if len(out) > size:
            raise corrupt(f"unpacks to more than {size} bytes")
    if len(out) != size:
        raise InputError(path, f"binary_compressed data unpacks to {len(out)} bytes, the header promises {size}")
    return bytes(out)


_COLUMNS = {"ascii": _ascii_columns, "binary": _binary_columns, "binary_compressed": _compressed_columns}
