"""Decode (and, for writing test/benchmark bags, pack) ``sensor_msgs/msg/PointCloud2`` data.

Decoding follows the message's own description only: ``fields`` (name, offset,
datatype, count), ``point_step``, ``row_step``, ``height``/``width`` and
``is_bigendian``; no layout is assumed. The cloud has ``height`` x ``width`` points;
``data`` must hold them (no more than ``row_step`` x ``height`` bytes, no fewer than
the last point needs), else ``InputError``. ``x y z`` are required, the intensity is the
first of ``INTENSITY_FIELDS`` present, and the per-point time the first of
``TIME_FIELDS``. Fields with ``count > 1`` contribute their first element.

Per-point time rule (result: float64 seconds *relative to the header stamp*):
- integer fields (INT8..UINT32, e.g. Ouster ``t``, Livox ``offset_time``) are
  nanoseconds relative to the stamp (32 bits cannot hold epoch nanoseconds);
- float fields (FLOAT32/FLOAT64, e.g. Velodyne ``time``, Hesai ``timestamp``) are
  seconds relative to the stamp, unless their median magnitude shows absolute
  epoch times: above 1e15 they are epoch nanoseconds (Livox PointCloud2
  ``timestamp``), above 1e6 epoch seconds; the header stamp is then subtracted.
Points are returned in the message's ``header.frame_id`` frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from flowslam.datasets.pcd import INTENSITY_FIELDS
from flowslam.errors import InputError

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TIME_FIELDS = ("t", "time", "timestamp", "offset_time", "time_offset")
"""Field names accepted as per-point time, first match wins."""

DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""``sensor_msgs/PointField`` datatype constants -> numpy type codes."""
_CODES = {v: k for k, v in DATATYPES.items()}

_ABS_NS = 1e15  # larger float times are epoch nanoseconds (1e15 s would be 30 My)
_ABS_S = 1e6  # larger float times are epoch seconds (11.6 days)


@dataclass
class DecodedCloud:
    """One decoded scan: ``points`` (N,3) float64 m, ``intensity`` and ``point_times`` (N,) float64 or None."""

    points: np.ndarray
    intensity: np.ndarray | None
    point_times: np.ndarray | None


def stamp_to_ns(stamp: Any) -> int:
    """A ``builtin_interfaces/Time`` (``sec``, ``nanosec``) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _pick(names: Mapping[str, Any], wanted: Sequence[str]) -> str | None:
    return next((w for w in wanted if w in names), None)


def decode_pointcloud2(msg: Any, where: str) -> DecodedCloud:
    """Decode a deserialized PointCloud2 (see module doc); ``InputError(where, ...)`` when malformed."""
    fields: dict[str, Any] = {}
    for f in msg.fields:
        fields.setdefault(f.name, f)  # a repeated name: the first one wins
    missing = [k for k in "xyz" if k not in fields]
    if missing:
        raise InputError(where, f"PointCloud2 has no field(s) {missing} (fields: {list(fields)})")
    wanted = ["x", "y", "z"]
    inten = _pick(fields, INTENSITY_FIELDS)
    tname = _pick(fields, TIME_FIELDS)
    wanted += [n for n in (inten, tname) if n]

    height, width = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for name in wanted:
        f = fields[name]
        code = DATATYPES.get(int(f.datatype))
        if code is None:
            raise InputError(where, f"PointCloud2 field {name!r} has unknown datatype {f.datatype}")
        if int(f.offset) + np.dtype(code).itemsize * max(int(f.count), 1) > step:
            raise InputError(where, f"PointCloud2 field {name!r} (offset {f.offset}) overruns point_step {step}")
        formats.append(order + code)
        offsets.append(int(f.offset))
    n = height * width
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if n and (step <= 0 or (height > 1 and row_step < width * step)):
        raise InputError(
            where, f"PointCloud2 point_step {step} / row_step {row_step} inconsistent with width {width}"
        )
    need = (height - 1) * row_step + width * step if n else 0
    if data.size < need:
        raise InputError(where, f"PointCloud2 data has {data.size} bytes, {height}x{width} points need {need}")
    if data.size > height * max(row_step, width * step):  # the message says data = row_step x height
        raise InputError(where, f"PointCloud2 data has {data.size} bytes, more than row_step {row_step} x height "
                                f"{height}: width/height/steps do not describe the data")
    if n == 0:
        empty = np.zeros((0,))
        return DecodedCloud(np.zeros((0, 3)), empty if inten else None, empty if tname else None)
    dt = np.dtype({"names": wanted, "formats": formats, "offsets": offsets, "itemsize": step})
    rec = np.ndarray(shape=(height, width), dtype=dt, buffer=data, strides=(row_step, step))

    def column(name: str) -> np.ndarray:
        return rec[name].reshape(-1)

    with np.errstate(invalid="ignore"):  # signalling NaNs in the data stay NaN (sanitize_frame drops them)
        points = np.column_stack([column(k).astype(np.float64) for k in "xyz"])
        intensity = column(inten).astype(np.float64) if inten else None
        times = _relative_times(column(tname), stamp_to_ns(msg.header.stamp)) if tname else None
    return DecodedCloud(points, intensity, times)


def _relative_times(raw: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Per-point times -> float64 seconds relative to the header stamp (rule in module doc)."""
    if np.issubdtype(raw.dtype, np.integer):
        return raw.astype(np.float64) * 1e-9
    vals = raw.astype(np.float64)
    finite = vals[np.isfinite(vals)]
    typical = float(np.median(np.abs(finite))) if finite.size else 0.0
    if typical > _ABS_NS:
        return (vals - float(stamp_ns)) * 1e-9
    if typical > _ABS_S:
        return (vals - stamp_ns // 1_000_000_000) - (stamp_ns % 1_000_000_000) * 1e-9
    return vals


def pack_points(
    columns: Mapping[str, np.ndarray],
    layout: Sequence[tuple[str | None, str]],
    *,
    big_endian: bool = False,
) -> tuple[list[tuple[str, int, int, int]], int, np.ndarray]:
    """Pack per-point columns into PointCloud2 records.

    ``layout`` lists ``(name, numpy code)`` in byte order, e.g.
    ``[("x", "f4"), ("y", "f4"), ("z", "f4"), (None, "u4"), ("t", "f8")]``; a ``None``
    name is padding. Returns ``(fields, point_step, data)`` with fields as
    ``(name, offset, datatype, count)`` and ``data`` a flat uint8 array.
    """
    order = ">" if big_endian else "<"
    names, formats, offsets, fields, off = [], [], [], [], 0
    for k, (name, code) in enumerate(layout):
        size = np.dtype(code).itemsize
        if name is not None:
            names.append(name)
            formats.append(order + code)
            offsets.append(off)
            fields.append((name, off, _CODES[np.dtype(code).str[1:]], 1))
        off += size
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": off})
    n = len(next(iter(columns.values())))
    rec = np.zeros(n, dtype=dt)
    for name in names:
        rec[name] = columns[name]
    return fields, off, rec.view(np.uint8).reshape(-1)
