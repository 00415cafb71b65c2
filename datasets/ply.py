"""A reader for ``.ply`` point clouds (``ascii``, ``binary_little_endian``, ``binary_big_endian``).

The ``vertex`` element gives the points: its ``x y z`` properties (required) in the
file's frame, metres; the first of ``INTENSITY_FIELDS`` present is the intensity.
Elements before ``vertex`` are skipped (in binary files only when they have no list
properties, whose size is not known without reading them); elements after it (faces,
...) are ignored. The data must hold every vertex the header declares: a shorter file
is an ``InputError``, never a partial or zero-filled cloud (Open3D's reader returns the
declared number of points from a truncated file).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowslam.datasets.pcd import INTENSITY_FIELDS
from flowslam.datasets.scan_files import read_file_bytes
from flowslam.errors import InputError

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER = 65536


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str]] = field(default_factory=list)
    """(name, numpy type code) of the scalar properties, in file order."""
    has_list: bool = False


@dataclass
class PlyHeader:
    format: str
    elements: list[PlyElement]
    data_offset: int


def parse_ply_header(raw: bytes, path: Path) -> PlyHeader:
    """Parse the header up to ``end_header``; ``InputError`` when it is not a valid PLY header."""
    end = raw.find(b"end_header", 0, _MAX_HEADER)
    if raw[:4] not in (b"ply\n", b"ply\r") or end < 0:
        raise InputError(path, "not a PLY file (no 'ply' ... 'end_header' header)")
    stop = raw.find(b"\n", end)
    data_offset = len(raw) if stop < 0 else stop + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()[1:]
    fmt, elements = None, []
    for n, line in enumerate(lines, 2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append(PlyElement(words[1], int(words[2])))
            elif words[0] == "property" and words[1] == "list":
                elements[-1].has_list = True
                _ = (_TYPES[words[2]], _TYPES[words[3]], words[4])
            elif words[0] == "property":
                elements[-1].properties.append((words[2], _TYPES[words[1]]))
            else:
                raise ValueError(words[0])
        except (IndexError, KeyError, ValueError) as e:
            raise InputError(path, f"malformed PLY header line {n} {line.strip()!r} ({e.__class__.__name__})") from None
    if fmt not in _FORMATS:
        raise InputError(path, f"unsupported PLY format {fmt!r} (use {', '.join(_FORMATS)})")
    bad = next((e for e in elements if e.count < 0), None)
    if bad is not None:
        raise InputError(path, f"PLY element {bad.name!r} has count {bad.count}")
    return PlyHeader(fmt, elements, data_offset)


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a .ply file -> ``(points (N,3) float64 m, intensity (N,) float64 | None)``, N = the
    ``vertex`` count of the header (module doc)."""
    path = Path(path)
    raw = read_file_bytes(path)
    hdr = parse_ply_header(raw, path)
    k = next((i for i, e in enumerate(hdr.elements) if e.name == "vertex"), None)
    if k is None:
        raise InputError(path, "PLY has no 'vertex' element")
    vertex = hdr.elements[k]
    names = [name for name, _ in vertex.properties]
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise InputError(path, f"PLY vertex has no property(ies) {missing} (has {names})")
    if vertex.has_list:
        raise InputError(path, "PLY vertex element has list properties (unsupported)")
    last = k == len(hdr.elements) - 1
    if hdr.format == "ascii":
        cols = _ascii_vertices(raw[hdr.data_offset:], hdr.elements[:k], vertex, last, path)
    else:
        cols = _binary_vertices(raw, hdr, k, last, path)
    inten = next((name for name in INTENSITY_FIELDS if name in cols), None)
    points = np.column_stack([cols[c].astype(np.float64) for c in "xyz"]).reshape(-1, 3)
    return points, (cols[inten].astype(np.float64) if inten else None)


def _record_dtype(element: PlyElement, order: str) -> np.dtype:
    names, formats = [], []
    for k, (name, code) in enumerate(element.properties):
        names.append(name if name not in names else f"{name}__{k}")  # a repeated name: the first one wins
        formats.append(order + code)
    return np.dtype({"names": names, "formats": formats})


def _binary_vertices(raw: bytes, hdr: PlyHeader, k: int, last: bool, path: Path) -> dict[str, np.ndarray]:
    """The vertex records; when ``vertex`` is the ``last`` element the data must end with them
    (up to one record's worth of slack, e.g. a newline)."""
    order = _FORMATS[hdr.format]
    offset = hdr.data_offset
    for e in hdr.elements[:k]:
        if e.has_list:
            raise InputError(path, f"PLY element {e.name!r} before 'vertex' has list properties (unsupported)")
        offset += e.count * _record_dtype(e, order).itemsize
    vertex = hdr.elements[k]
    dt = _record_dtype(vertex, order)
    need = vertex.count * dt.itemsize
    have = len(raw) - offset
    if have < need:
        raise InputError(path, f"binary PLY data has {max(have, 0)} bytes for {vertex.count} vertices x "
                               f"{dt.itemsize} bytes = {need} (truncated .ply?)")
    if last and have >= need + dt.itemsize:
        raise InputError(path, f"binary PLY data has {have} bytes, more than its {vertex.count} vertices x "
                               f"{dt.itemsize} bytes = {need}: the header does not describe the data")
    rec = np.frombuffer(raw, dtype=dt, count=vertex.count, offset=offset)
    return {name: rec[name] for name in dt.names}


def _ascii_vertices(
    data: bytes, before: list[PlyElement], vertex: PlyElement, last: bool, path: Path
) -> dict[str, np.ndarray]:
    """The vertex lines (one per vertex, after one line per instance of the ``before`` elements);
    when ``vertex`` is the ``last`` element no other lines may follow."""
    lines = [ln for ln in data.splitlines() if ln.strip()]
    skip = sum(e.count for e in before)
    rows = lines[skip:skip + vertex.count]
    if len(rows) < vertex.count:
        raise InputError(path, f"ASCII PLY data has {len(rows)} vertex lines, the header declares "
                               f"{vertex.count} (truncated .ply?)")
    if last and len(lines) > skip + vertex.count:
        raise InputError(path, f"ASCII PLY data has {len(lines) - skip} lines after the header, more than its "
                               f"{vertex.count} vertices: the header does not describe the data")
    width = len(vertex.properties)
    try:
        values = np.array(b" ".join(rows).split(), dtype=np.float64)
    except ValueError:
        raise InputError(path, "ASCII PLY vertex data contains non-numeric values") from None
    if values.size != vertex.count * width:
        raise InputError(path, f"ASCII PLY vertex lines hold {values.size} numbers, expected {vertex.count} x "
                               f"{width} properties")
    table = values.reshape(vertex.count, width)
    cols: dict[str, np.ndarray] = {}
    for j, (name, _code) in enumerate(vertex.properties):
        cols.setdefault(name, table[:, j])
    return cols
