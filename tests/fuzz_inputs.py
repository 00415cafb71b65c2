"""Generators of valid and broken reader inputs, and the property every reader must keep.

Shared by the CI fuzz test (``tests/test_fuzz_readers.py``) and the long run
(``tools/fuzz_readers.py``, which puts ``tests/`` on ``sys.path``).

For each reader in ``READERS`` a Hypothesis strategy (``cases(name)``) builds a valid
input from a random cloud or trajectory (sizes, layouts, encodings, values up to float32's
limits, NaN, inf) and applies one mutation (none, truncation, byte flips, inserted or
appended bytes, a changed header field, a wrong count, an empty file, ...). Each
``Case`` knows what a correct reader may answer: the point/pose counts a valid result
may have (from the header and the data, so that a silent truncation is a failure),
whether it must succeed, and for unbroken inputs the exact values.

``check(case, folder)`` runs the reader on the case (files are written into ``folder``)
and raises ``AssertionError`` when the property is broken: the answer must be either a
valid result (points (N,3) float64 with N allowed, intensity (N,) or None; after
``sanitize_frame`` finite points within ``max_coordinate_m``; trajectories of rigid
poses, TUM stamps increasing) or an ``InputError`` whose message is one line, never
any other exception.
"""

from __future__ import annotations

import io
import re
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from flowslam import geometry
from flowslam.errors import InputError
from flowslam.frame import MAX_COORDINATE_M, Frame, sanitize_frame

TRIED: Counter = Counter()
"""Inputs tried per reader (``check`` counts)."""
OUTCOMES: Counter = Counter()
"""(reader, "valid" | "InputError") -> count."""


@dataclass
class Case:
    """One generated input and what a correct reader may answer."""

    reader: str
    payload: Any
    """File bytes, or a PointCloud2 message object (``pointcloud2``)."""
    mutation: str
    allowed: frozenset | None
    """Counts a valid result may have; empty = must raise ``InputError``; None = ask ``oracle``."""
    must_succeed: bool = False
    expected: np.ndarray | None = None
    """For must-succeed cases: the exact points (as float32) or poses."""
    options: dict = field(default_factory=dict)

    def __repr__(self) -> str:  # short, for Hypothesis' falsifying-example report
        size = len(self.payload) if isinstance(self.payload, (bytes, bytearray)) else "-"
        head = bytes(self.payload[:160]) if isinstance(self.payload, (bytes, bytearray)) else self.payload
        return (f"Case({self.reader}, {self.mutation}, allowed={set(self.allowed) if self.allowed is not None else None}, "
                f"must_succeed={self.must_succeed}, {size} bytes, head={head!r})")


# ---------------------------------------------------------------- clouds and byte mutations
VALUE_KINDS = ("normal", "normal", "huge", "nan", "inf", "extreme", "tiny", "integers")


@st.composite
def clouds(draw, max_points: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """(points (N,3) float32, intensity (N,) float32) with an occasional nasty value mix."""
    n = draw(st.integers(0, max_points))
    kind = draw(st.sampled_from(VALUE_KINDS))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    pts = rng.normal(0.0, 20.0, (n, 3)).astype(np.float32)
    if n:
        pick = rng.random((n, 3)) < 0.2
        if kind == "huge":
            pts *= np.float32(10.0 ** rng.integers(3, 36))
        elif kind == "nan":
            pts[pick] = np.nan
        elif kind == "inf":
            pts[pick] = np.float32(np.inf) * rng.choice([-1, 1], size=int(pick.sum()))
        elif kind == "extreme":
            pts[pick] = np.finfo(np.float32).max * rng.choice([-1, 1], size=int(pick.sum()))
        elif kind == "tiny":
            pts[pick] = np.float32(1e-45)
        elif kind == "integers":
            pts = np.round(pts)
    inten = rng.uniform(0.0, 1.0, n).astype(np.float32)
    return pts, inten


BYTE_MUTATIONS = ("none", "truncate", "flip", "flip3", "insert", "delete", "append", "empty")


@st.composite
def byte_mutation(draw, data: bytes) -> tuple[bytes, str, int]:
    """(mutated bytes, kind, position) for a kind of ``BYTE_MUTATIONS``."""
    kind = draw(st.sampled_from(BYTE_MUTATIONS))
    n = len(data)
    pos = draw(st.integers(0, max(n - 1, 0)))
    if kind == "none" or (n == 0 and kind not in ("insert", "append")):
        return data, "none", 0
    if kind == "truncate":
        return data[:pos], kind, pos
    if kind in ("flip", "flip3"):
        out = bytearray(data)
        for _ in range(1 if kind == "flip" else 3):
            p = draw(st.integers(0, n - 1))
            out[p] ^= draw(st.integers(1, 255))
        return bytes(out), kind, pos
    if kind == "insert":
        extra = draw(st.binary(min_size=1, max_size=8))
        return data[:pos] + extra + data[pos:], kind, pos
    if kind == "delete":
        k = draw(st.integers(1, 8))
        return data[:pos] + data[pos + k:], kind, pos
    if kind == "append":
        return data + draw(st.binary(min_size=1, max_size=40)), kind, n
    return b"", "empty", 0


# ---------------------------------------------------------------- KITTI .bin
@st.composite
def kitti_bin_cases(draw) -> Case:
    pts, inten = draw(clouds())
    data = np.column_stack([pts, inten]).astype("<f4").tobytes()
    out, kind, _ = draw(byte_mutation(data))
    ok = len(out) % 16 == 0
    return Case("kitti_bin", out, kind, frozenset({len(out) // 16}) if ok else frozenset(), must_succeed=ok,
                expected=pts if kind == "none" else None)


# ---------------------------------------------------------------- PCD
PCD_TYPES = {"f4": ("F", 4), "f8": ("F", 8), "u1": ("U", 1), "u2": ("U", 2), "i4": ("I", 4), "u4": ("U", 4)}


def lzf_compress(data: bytes) -> bytes:
    """A small greedy LZF compressor (liblzf's format): literal runs and back references."""
    out, lit = bytearray(), bytearray()
    table: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush() -> None:
        for k in range(0, len(lit), 32):
            chunk = lit[k:k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        lit.clear()

    while i < n:
        key = data[i:i + 3]
        ref = table.get(key) if len(key) == 3 else None
        table[key] = i
        if ref is not None and 0 < i - ref <= 8192:
            length = 3
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            off = i - ref - 1
            code = length - 2
            if code < 7:
                out.append((code << 5) | (off >> 8))
            else:
                out.append((7 << 5) | (off >> 8))
                out.append(code - 7)
            out.append(off & 0xFF)
            i += length
        else:
            lit.append(data[i])
            i += 1
    flush()
    return bytes(out)


@st.composite
def pcd_layouts(draw) -> list[tuple[str, str, int]]:
    """(name, numpy code, count) per field: x y z (f4 or f8) in any order, maybe intensity, padding, extras."""
    xyz = draw(st.sampled_from(["f4", "f4", "f8"]))
    fields = [(c, xyz, 1) for c in "xyz"]
    if draw(st.booleans()):
        fields.append(("intensity", draw(st.sampled_from(["f4", "u1", "u2"])), 1))
    if draw(st.booleans()):
        fields.append(("_", "u1", draw(st.integers(1, 4))))
    if draw(st.booleans()):
        fields.append(("normal", "f4", 3))
    if draw(st.booleans()):
        fields.append(("ring", "u2", 1))
    return draw(st.permutations(fields))


def _pcd_column(name: str, pts: np.ndarray, inten: np.ndarray, code: str, count: int) -> np.ndarray:
    n = len(pts)
    if name in "xyz":
        col = pts[:, "xyz".index(name)].astype(code)
    elif name == "intensity":
        col = inten.astype(np.float64) * (255 if code == "u1" else 1000 if code == "u2" else 1)
        col = col.astype(code)
    else:
        col = (np.arange(n * count) % 7).astype(code)
    return col.reshape(n, count) if count > 1 else col


def pcd_bytes(pts, inten, layout, data: str, height: int, points: int | None = None) -> tuple[bytes, int]:
    """(file bytes, offset of the data) of a PCD v0.7 file."""
    n = len(pts)
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(f for f, _, _ in layout),
        "SIZE " + " ".join(str(PCD_TYPES[c][1]) for _, c, _ in layout),
        "TYPE " + " ".join(PCD_TYPES[c][0] for _, c, _ in layout),
        "COUNT " + " ".join(str(k) for _, _, k in layout),
        f"WIDTH {n // height if height else 0}",
        f"HEIGHT {height}",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n if points is None else points}",
        f"DATA {data}",
    ]
    head = ("\n".join(header) + "\n").encode()
    cols = [_pcd_column(f, pts, inten, c, k) for f, c, k in layout]
    if data == "ascii":
        buf = io.StringIO()
        for row in range(n):
            vals = []
            for col in cols:
                vals += [repr(float(v)) if col.dtype.kind == "f" else str(int(v)) for v in np.ravel(col[row])]
            buf.write(" ".join(vals) + "\n")
        body = buf.getvalue().encode()
    elif data == "binary":
        rec = b"".join(b"".join(col[row].astype("<" + col.dtype.str[1:]).tobytes() for col in cols)
                       for row in range(n))
        body = rec
    else:
        raw = b"".join(col.astype("<" + col.dtype.str[1:]).tobytes() for col in cols)
        packed = lzf_compress(raw)
        body = struct.pack("<II", len(packed), len(raw)) + packed
    return head + body, len(head)


def _set_header_value(data: bytes, key: str, value: str) -> bytes:
    return re.sub(rb"(?m)^" + key.encode() + rb" [^\n]*$", (key + " " + value).encode(), data, count=1)


@st.composite
def pcd_cases(draw) -> Case:
    pts, inten = draw(clouds())
    n = len(pts)
    layout = draw(pcd_layouts())
    mode = draw(st.sampled_from(["ascii", "binary", "binary_compressed"]))
    divisors = [h for h in (1, 2, 3, 4) if n % h == 0] if n else [1]
    height = draw(st.sampled_from(divisors))
    data, offset = pcd_bytes(pts, inten, layout, mode, height)
    N = frozenset({n})
    kind = draw(st.sampled_from(["bytes", "bytes", "points", "width", "height", "field", "drop_line", "extra_records"]))
    if kind == "points":  # the case: a wrong POINTS must not drop points
        p = draw(st.integers(0, 10**6).filter(lambda v: v != n))
        return Case("pcd", _set_header_value(data, "POINTS", str(p)), "points", N, True, pts)
    if kind in ("width", "height"):
        key = kind.upper()
        v = draw(st.integers(-2, 10**6))
        out = _set_header_value(data, key, str(v))
        w, h = (v, height) if key == "WIDTH" else (n // height, v)
        return Case("pcd", out, f"{kind}={v}", N if w * h == n and v >= 0 else frozenset())
    if kind == "field":
        key = draw(st.sampled_from(["FIELDS", "SIZE", "TYPE", "COUNT", "DATA"]))
        token = draw(st.sampled_from(["x", "w", "4", "8", "0", "-1", "F", "U", "Q", "ascii", "binary",
                                      "binary_compressed", "", "1 1"]))
        line = re.search(rb"(?m)^" + key.encode() + rb" ([^\n]*)$", data)
        vals = line.group(1).decode().split()
        vals[draw(st.integers(0, len(vals) - 1))] = token
        return Case("pcd", _set_header_value(data, key, " ".join(vals)), f"{key} {token}", N)
    if kind == "drop_line":
        lines = data[:offset].split(b"\n")
        k = draw(st.integers(0, len(lines) - 2))
        return Case("pcd", b"\n".join(lines[:k] + lines[k + 1:]) + data[offset:], f"drop {lines[k][:8]!r}", N)
    if kind == "extra_records":  # data for more points than WIDTH x HEIGHT: never silently ignored
        more, _ = pcd_bytes(*draw(clouds(max_points=4)), layout, "ascii" if mode == "ascii" else "binary", 1)
        extra = more[more.index(b"DATA") :].split(b"\n", 1)[1]
        if mode == "binary_compressed" or not extra:
            return Case("pcd", data, "none", N, True, pts)
        return Case("pcd", data + extra, "extra records", frozenset())
    out, how, pos = draw(byte_mutation(data))
    if how == "none":
        return Case("pcd", out, "none", N, True, pts)
    if mode != "ascii" and (how in ("truncate", "empty") or (how == "delete" and pos >= offset)):
        return Case("pcd", out, f"{how}@{pos} {mode}", frozenset())
    if how == "append" and mode == "binary":
        rec = sum(PCD_TYPES[c][1] * k for _, c, k in layout)
        return Case("pcd", out, f"append {len(out) - len(data)} {mode}", N if len(out) - len(data) < rec else frozenset())
    return Case("pcd", out, f"{how}@{pos} {mode}", N)


# ---------------------------------------------------------------- PLY
PLY_TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "u2": "ushort", "i4": "int"}


def ply_bytes(pts, inten, props: list[tuple[str, str]], fmt: str, count: int | None = None) -> tuple[bytes, int]:
    n = len(pts)
    head = ["ply", f"format {fmt} 1.0", "comment flowslam fuzz", f"element vertex {n if count is None else count}"]
    head += [f"property {PLY_TYPES[c]} {name}" for name, c in props]
    head = ("\n".join(head + ["end_header"]) + "\n").encode()
    cols = [_pcd_column(name, pts, inten, c, 1) for name, c in props]
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(col[r])) if col.dtype.kind == "f" else str(int(col[r])) for col in cols) + "\n"
                       for r in range(n)).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(f"f{k}", order + c) for k, (_, c) in enumerate(props)])
        rec = np.zeros(n, dt)
        for k, col in enumerate(cols):
            rec[f"f{k}"] = col
        body = rec.tobytes()
    return head + body, len(head)


@st.composite
def ply_cases(draw) -> Case:
    pts, inten = draw(clouds())
    n = len(pts)
    xyz = draw(st.sampled_from(["f4", "f8"]))
    props = [(c, xyz) for c in "xyz"]
    if draw(st.booleans()):
        props.append(("intensity", draw(st.sampled_from(["f4", "u1", "u2"]))))
    if draw(st.booleans()):
        props.append(("red", "u1"))
    props = draw(st.permutations(props))
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"]))
    data, offset = ply_bytes(pts, inten, props, fmt)
    N = frozenset({n})
    kind = draw(st.sampled_from(["bytes", "bytes", "count", "format", "property", "extra_vertices"]))
    if kind == "count":
        c = draw(st.integers(-1, 10**6))
        return Case("ply", ply_bytes(pts, inten, props, fmt, c)[0], f"count={c} {fmt}", N if c == n else frozenset())
    if kind == "format":
        f2 = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "binary", "1.0"]))
        return Case("ply", data.replace(f"format {fmt}".encode(), f"format {f2}".encode(), 1), f"format {f2}", N)
    if kind == "property":
        bad = draw(st.sampled_from(["property float", "property list uchar int x", "property", "property int8 x",
                                    "element face 3", "property quux y"]))
        lines = data[:offset].split(b"\n")
        k = draw(st.integers(4, len(lines) - 2))
        lines.insert(k, bad.encode())
        return Case("ply", b"\n".join(lines) + data[offset:], f"insert {bad!r}", N)
    if kind == "extra_vertices":
        more, off2 = ply_bytes(*draw(clouds(max_points=4)), props, fmt)
        if len(more) == off2:
            return Case("ply", data, "none", N, True, pts)
        return Case("ply", data + more[off2:], "extra vertices", frozenset())
    out, how, pos = draw(byte_mutation(data))
    if how == "none":
        return Case("ply", out, "none", N, True, pts)
    if fmt != "ascii" and (how in ("truncate", "empty") or (how == "delete" and pos >= offset)):
        return Case("ply", out, f"{how}@{pos} {fmt}", frozenset())
    if how == "append" and fmt != "ascii":
        rec = sum(np.dtype(c).itemsize for _, c in props)
        return Case("ply", out, f"append {fmt}", N if len(out) - len(data) < rec else frozenset())
    return Case("ply", out, f"{how}@{pos} {fmt}", N)


# ---------------------------------------------------------------- NPY
@st.composite
def npy_cases(draw) -> Case:
    pts, inten = draw(clouds())
    n = len(pts)
    shape_kind = draw(st.sampled_from(["n3", "n4", "n5", "struct", "fortran"] * 2
                                      + ["flat", "complex", "object", "npz", "bool", "3d"]))
    dtype = draw(st.sampled_from(["<f4", "<f8", ">f4", "<f2", "<i4"]))
    buf = io.BytesIO()
    with np.errstate(all="ignore"):  # float16 / int32 casts of huge or NaN values
        _save_npy(buf, shape_kind, dtype, pts, inten)
    data = buf.getvalue()
    valid = shape_kind in ("n3", "n4", "n5", "struct", "fortran")
    N = frozenset({n}) if valid else frozenset()
    with np.errstate(all="ignore"):
        expected = pts.astype(dtype).astype(np.float32) if valid and dtype != "<i4" else None
    if draw(st.integers(0, 4)) == 0 and valid:  # a wrong shape in the header
        m = draw(st.integers(0, 10**12))
        out = re.sub(rb"'shape': \((\d+),", f"'shape': ({m},".encode(), data, count=1)
        return Case("npy", out, f"shape {m} {shape_kind}", N if m == n else frozenset())
    out, how, pos = draw(byte_mutation(data))
    if how == "none":
        return Case("npy", out, f"none {shape_kind}", N, valid, expected)
    if how in ("truncate", "append", "empty"):
        return Case("npy", out, f"{how} {shape_kind}", frozenset())
    # a flip may turn complex64 into float64 or bool into uint8: a valid (n, 3) array then
    return Case("npy", out, f"{how}@{pos} {shape_kind}", frozenset({n}))


def _save_npy(buf: io.BytesIO, shape_kind: str, dtype: str, pts: np.ndarray, inten: np.ndarray) -> None:
    n = len(pts)
    if shape_kind in ("n3", "n4", "n5", "fortran"):
        cols = {"n3": 3, "n4": 4, "n5": 5, "fortran": 4}[shape_kind]
        arr = np.column_stack([pts, inten, np.zeros(n, np.float32)])[:, :cols].astype(dtype)
        np.save(buf, np.asfortranarray(arr) if shape_kind == "fortran" else arr)
    elif shape_kind == "struct":
        arr = np.zeros(n, dtype=[("intensity", "<f4"), ("x", dtype), ("y", dtype), ("z", dtype)])
        for k, c in enumerate("xyz"):
            arr[c] = pts[:, k]
        np.save(buf, arr)
    elif shape_kind == "flat":
        np.save(buf, pts.reshape(-1))
    elif shape_kind == "complex":
        np.save(buf, pts.astype(np.complex64))
    elif shape_kind == "object":
        np.save(buf, np.array([[1.0, 2.0, 3.0]] * max(n, 1), dtype=object), allow_pickle=True)
    elif shape_kind == "bool":
        np.save(buf, pts > 0)
    elif shape_kind == "3d":
        np.save(buf, np.zeros((n, 3, 1), np.float32))
    else:
        np.savez(buf, points=pts)


# ---------------------------------------------------------------- PointCloud2
PC2_LAYOUTS = (
    (("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4")),
    (("x", "f4"), ("y", "f4"), ("z", "f4"), (None, "u4"), ("intensity", "f4"), ("t", "u4")),
    (("t", "f8"), ("z", "f8"), ("y", "f8"), ("x", "f8")),
    (("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u2"), ("ring", "u2"), ("time", "f4")),
)


def _typestore(kind: str = "ros2"):
    from flowslam.datasets.rosbag_writer import typestore_for

    return typestore_for("ros1" if kind == "ros1" else "mcap")


@st.composite
def pointcloud2_cases(draw) -> Case:
    from flowslam.datasets.rosbag_writer import make_pointcloud2

    pts, inten = draw(clouds())
    n = len(pts)
    layout = draw(st.sampled_from(PC2_LAYOUTS))
    heights = [h for h in (1, 2, 4) if n % h == 0] if n else [1]
    height = draw(st.sampled_from(heights))
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": inten * 100,
            "t": np.arange(n) * 1000, "ring": np.arange(n) % 16, "time": np.arange(n) * 1e-5}
    ros = draw(st.sampled_from(["ros2", "ros1"]))
    ts = _typestore(ros)
    opts = {"ros1": ros == "ros1"}
    msg = make_pointcloud2(ts, 1_700_000_000_000_000_000, cols, layout, big_endian=draw(st.booleans()),
                           height=height, row_padding=draw(st.sampled_from([0, 0, 3])))
    kind = draw(st.sampled_from(["none", "attr", "attr", "data", "field", "cdr"]))
    exact = pts.astype(dict(layout)["x"]).astype(np.float32)
    if kind == "none":
        return Case("pointcloud2", msg, "none", frozenset({n}), True, exact, opts)
    if kind == "cdr":  # the serialized message, mutated, through the reader's deserializer
        serialize = ts.serialize_ros1 if opts["ros1"] else ts.serialize_cdr
        out, how, pos = draw(byte_mutation(bytes(serialize(msg, "sensor_msgs/msg/PointCloud2"))))
        return Case("pointcloud2", out, f"{ros} bytes {how}@{pos}", None, options=opts)
    if kind == "attr":
        name = draw(st.sampled_from(["width", "height", "point_step", "row_step", "is_bigendian"]))
        value = not msg.is_bigendian if name == "is_bigendian" else draw(
            st.sampled_from([0, 1, 2, 3, 7, 16, 2**31, 2**32 - 1, getattr(msg, name) + 1, getattr(msg, name) - 1]))
        if name != "is_bigendian":
            value = max(int(value), 0)
        setattr(msg, name, value)
        return Case("pointcloud2", msg, f"{name}={value}", None, options=opts)
    if kind == "data":
        out, how, pos = draw(byte_mutation(msg.data.tobytes()))
        msg.data = np.frombuffer(out, np.uint8)
        longer = len(out) > msg.row_step * msg.height  # more data than the message describes
        return Case("pointcloud2", msg, f"data {how}@{pos}", frozenset() if longer else None, options=opts)
    f = draw(st.sampled_from(msg.fields))
    what = draw(st.sampled_from(["offset", "datatype", "count", "name"]))
    value = draw({"offset": st.sampled_from([0, 1, 3, 4, 8, 255, 2**31]), "datatype": st.integers(0, 10),
                  "count": st.sampled_from([0, 1, 2, 1000]), "name": st.sampled_from(["x", "y", "q", "", "t"])}[what])
    setattr(f, what, value)
    return Case("pointcloud2", msg, f"field {f.name}.{what}={value}", None, options=opts)


# ---------------------------------------------------------------- trajectory files
@st.composite
def trajectories(draw) -> tuple[np.ndarray, np.ndarray]:
    n = draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = geometry.from_quat_xyzw(q, rng.normal(0, 50, (n, 3)))
    stamps = 1e3 * draw(st.integers(0, 2)) + np.cumsum(rng.uniform(0.01, 1.0, n))
    return poses, stamps


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


@st.composite
def trajectory_cases(draw, fmt: str) -> Case:
    from flowslam.trajectory import Trajectory, write_kitti, write_tum

    poses, stamps = draw(trajectories())
    buf = io.BytesIO()
    (write_tum if fmt == "tum" else write_kitti)(buf, Trajectory(poses, stamps))
    text = buf.getvalue().decode()
    lines = text.splitlines()
    data_rows = [k for k, ln in enumerate(lines) if not ln.startswith("#")]
    n = len(data_rows)
    reader = f"trajectory_{fmt}"
    kind = draw(st.sampled_from(["none", "bytes", "bytes", "token", "drop_token", "rotation", "duplicate", "swap",
                                 "crlf", "commas", "empty", "comments"]))
    if kind in ("none", "crlf", "commas"):
        out = text.replace("\n", "\r\n") if kind == "crlf" else text
        if kind == "commas":
            out = "\n".join(",".join(ln.split()) if not ln.startswith("#") else ln for ln in lines) + "\n"
        return Case(reader, out.encode(), kind, frozenset({n}), True, poses)
    if kind in ("empty", "comments"):
        return Case(reader, b"" if kind == "empty" else b"# nothing\n\n   \n", kind, frozenset())
    row = draw(st.sampled_from(data_rows))
    toks = lines[row].split()
    if kind == "token":
        k = draw(st.integers(0, len(toks) - 1))
        toks[k] = draw(st.sampled_from(["abc", "nan", "inf", "-inf", "1e999", "1e308", "-0", "0x10", "1,5", "--1"]))
        lines[row] = " ".join(toks)
        return Case(reader, ("\n".join(lines) + "\n").encode(), f"token {toks[k]}@{k}", None)
    if kind == "drop_token":
        del toks[draw(st.integers(0, len(toks) - 1))]
        lines[row] = " ".join(toks)
        return Case(reader, ("\n".join(lines) + "\n").encode(), "drop token", frozenset())
    if kind == "rotation":  # a rotation entry (KITTI) or quaternion component (TUM) off by delta
        delta = draw(st.sampled_from([0.5, 0.05, 1e-3]))
        k = draw(st.sampled_from([0, 1, 2, 4, 5, 6, 8, 9, 10] if fmt == "kitti" else [4, 5, 6, 7]))
        toks[k] = repr(float(toks[k]) + delta)
        lines[row] = " ".join(toks)
        allowed = frozenset({n}) if fmt == "tum" else frozenset()  # TUM quaternions are normalised
        return Case(reader, ("\n".join(lines) + "\n").encode(), f"rotation {k}+{delta}", allowed, fmt == "tum")
    if kind == "duplicate":
        lines.insert(row, lines[row])
        out = ("\n".join(lines) + "\n").encode()
        return Case(reader, out, "duplicate line", frozenset() if fmt == "tum" else frozenset({n + 1}), fmt != "tum")
    if kind == "swap":
        if n < 2:
            return Case(reader, text.encode(), "none", frozenset({n}), True, poses)
        a, b = data_rows[0], data_rows[-1]
        lines[a], lines[b] = lines[b], lines[a]
        out = ("\n".join(lines) + "\n").encode()
        return Case(reader, out, "swap lines", frozenset() if fmt == "tum" else frozenset({n}), fmt != "tum")
    out, how, pos = draw(byte_mutation(text.encode()))
    return Case(reader, out, f"{how}@{pos}", None)


# ---------------------------------------------------------------- the readers and the property
def _read_scan_file(suffix: str) -> Callable[[Case, Path], tuple]:
    def read(case: Case, folder: Path):
        from flowslam.datasets.scan_files import read_scan

        path = folder / f"scan{suffix}"
        path.write_bytes(case.payload)
        return read_scan(path)

    return read


def _read_pointcloud2(case: Case, folder: Path):
    from flowslam.datasets.pointcloud2 import decode_pointcloud2

    msg = case.payload
    if isinstance(msg, (bytes, bytearray)):
        from flowslam.datasets.rosbag import deserialize_message

        ts = _typestore("ros1" if case.options.get("ros1") else "ros2")
        deserialize = ts.deserialize_ros1 if case.options.get("ros1") else ts.deserialize_cdr
        msg = deserialize_message(deserialize, msg, "sensor_msgs/msg/PointCloud2", "fuzz.bag [#0]")
    case.options["declared"] = int(msg.height) * int(msg.width)
    cloud = decode_pointcloud2(msg, "fuzz.bag [#0]")
    return cloud.points, cloud.intensity


def _read_trajectory(case: Case, folder: Path):
    from flowslam.trajectory import read_trajectory

    path = folder / "poses.txt"
    path.write_bytes(case.payload)
    return read_trajectory(path)


READERS: dict[str, tuple[Callable[[], st.SearchStrategy], Callable[[Case, Path], Any]]] = {
    "kitti_bin": (kitti_bin_cases, _read_scan_file(".bin")),
    "pcd": (pcd_cases, _read_scan_file(".pcd")),
    "ply": (ply_cases, _read_scan_file(".ply")),
    "npy": (npy_cases, _read_scan_file(".npy")),
    "pointcloud2": (pointcloud2_cases, _read_pointcloud2),
    "trajectory_tum": (lambda: trajectory_cases("tum"), _read_trajectory),
    "trajectory_kitti": (lambda: trajectory_cases("kitti"), _read_trajectory),
}
"""Reader name -> (strategy of ``Case``, function running the reader on a case)."""


def cases(name: str) -> st.SearchStrategy:
    return READERS[name][0]()


def _allowed_counts(case: Case) -> frozenset:
    if case.allowed is not None:
        return case.allowed
    if case.reader == "pointcloud2":
        return frozenset({case.options["declared"]})
    if case.reader.startswith("trajectory"):
        try:
            return frozenset({len(_lines(case.payload.decode()))})
        except UnicodeDecodeError:
            return frozenset()
    raise AssertionError(f"no count oracle for {case.reader}")


def _check_cloud(case: Case, result: Any, allowed: frozenset) -> None:
    points, intensity = result
    assert isinstance(points, np.ndarray) and points.dtype == np.float64, type(points)
    assert points.ndim == 2 and points.shape[1] == 3, points.shape
    n = len(points)
    assert n in allowed, f"{n} points, allowed {sorted(allowed)} (silent truncation or invented points)"
    assert intensity is None or (intensity.dtype == np.float64 and intensity.shape == (n,)), intensity
    if case.expected is not None:
        np.testing.assert_array_equal(points.astype(np.float32), case.expected)
    frame = Frame(0, 0.0, points, intensity, source="fuzz")
    try:
        frame = sanitize_frame(frame, min_points=1)
    except InputError as e:
        _check_error(e)
        return
    assert np.isfinite(frame.points).all() and (np.abs(frame.points) <= MAX_COORDINATE_M).all()
    assert frame.intensity is None or len(frame.intensity) == len(frame.points)


def _check_trajectory(case: Case, traj: Any, allowed: frozenset) -> None:
    assert len(traj) in allowed, f"{len(traj)} poses, allowed {sorted(allowed)}"
    assert all(geometry.is_se3(T, tol=1e-4) for T in traj.poses)
    if traj.timestamps is not None:
        assert np.isfinite(traj.timestamps).all() and (np.diff(traj.timestamps) > 0).all(), traj.timestamps
    if case.expected is not None:
        np.testing.assert_allclose(traj.poses, case.expected, rtol=1e-6, atol=1e-6)


def _check_error(e: InputError) -> None:
    text = str(e)
    assert "\n" not in text and "\r" not in text and len(text.splitlines()) == 1, repr(text)


def check(case: Case, folder: Path) -> str:
    """Run the case's reader and assert the property (module doc); returns "valid" or "InputError"."""
    TRIED[case.reader] += 1
    try:
        with np.errstate(all="ignore"):  # e.g. casting a signalling NaN that a byte flip made
            result = READERS[case.reader][1](case, folder)
    except InputError as e:
        assert not case.must_succeed, f"must succeed but raised: {e}"
        _check_error(e)
        outcome = "InputError"
    else:
        allowed = _allowed_counts(case)
        if case.reader.startswith("trajectory"):
            _check_trajectory(case, result, allowed)
        else:
            _check_cloud(case, result, allowed)
        outcome = "valid"
    OUTCOMES[case.reader, outcome] += 1
    return outcome


def fuzz(reader: str, folder: Path, max_examples: int, *, derandomize: bool = True, run_seed: int | None = None) -> int:
    """Run Hypothesis on ``reader`` for ``max_examples`` inputs (deterministic with ``derandomize``,
    else from ``run_seed``); a broken property raises (after shrinking). Returns the inputs tried."""
    before = TRIED[reader]
    config = settings(max_examples=max_examples, deadline=None, derandomize=derandomize, database=None,
                      print_blob=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

    @config
    @given(case=cases(reader))
    def run(case: Case) -> None:
        check(case, folder)

    if run_seed is not None and not derandomize:
        run = seed(run_seed)(run)
    run()
    return TRIED[reader] - before
