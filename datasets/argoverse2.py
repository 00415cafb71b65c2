"""Argoverse 2 sensor-log reader (``sensors/lidar/<timestamp_ns>.feather`` + poses + flow labels).

Frames: AV2 stores each merged sweep (both roof LiDARs) in the *egovehicle* frame,
so for this reader flowslam's "sensor frame" **is the egovehicle frame**; GT poses
are ``T_city_egovehicle`` (``city_SE3_egovehicle.feather``, ~200 Hz, interpolated by
slerp/linear to the sweep timestamp when there is no exact match). The LiDARs'
own extrinsics ``T_egovehicle_sensor`` (``calibration/egovehicle_SE3_sensor.feather``)
are kept in ``Argoverse2Log.egovehicle_SE3_sensor`` and ``Frame.extras``.

Units: metres; ``timestamp`` = sweep ``timestamp_ns`` * 1e-9 (seconds, epoch; strictly
increasing, else ``InputError`` or with ``fix_times`` a logged repair);
``point_times`` = ``offset_ns`` * 1e-9, seconds relative to the sweep timestamp.

Scene-flow labels (``flow_tx_m flow_ty_m flow_tz_m classes dynamic is_ground_0``):
flow of sweep *i* to sweep *i+1*, expressed in the sweep-(i+1) ego frame, total
displacement including ego motion, i.e. flowslam's ``gt_flow`` convention. They
sit on frame *i* (one row per point of sweep *i*, checked). Looked up as
``flow_labels/<timestamp_ns>.feather`` for sweep *i*, or the single
``flow_labels.feather`` at the log root, which labels the first sweep (the layout
of the av2-api test logs). ``is_ground_0`` goes to ``Frame.extras["is_ground"]``, the classes also to
``Frame.extras["av2_category"]`` (what the scene-flow metrics read from every reader).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from flowslam import geometry
from flowslam.frame import Dataset, Frame
from flowslam.datasets.pose_interpolation import ScanPoses, poses_at_scans
from flowslam.errors import InputError
from flowslam.trajectory import checked_timestamps, unit_quaternions

log = logging.getLogger(__name__)

LIDAR_COLUMNS = ("x", "y", "z", "intensity", "offset_ns")
POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
FLOW_COLUMNS = ("flow_tx_m", "flow_ty_m", "flow_tz_m", "classes", "dynamic", "is_ground_0")
POINT_EXTRAS = ("laser_number", "is_ground", "av2_category")
"""Per-point arrays this reader keeps in ``Frame.extras`` (filtered with the points by ``sanitize_frame``)."""


def read_feather_columns(
    path: Path, columns: tuple[str, ...], optional: tuple[str, ...] = ()
) -> dict[str, np.ndarray]:
    """Read the named columns of a feather file as numpy arrays; ``InputError`` when absent/unreadable."""
    import pyarrow as pa
    import pyarrow.feather as feather

    try:
        table = feather.read_table(path)
    except FileNotFoundError:
        raise InputError(path, "file does not exist") from None
    except (pa.ArrowException, OSError) as e:
        raise InputError(path, f"not a readable feather file ({e.__class__.__name__}: {e})") from None
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise InputError(path, f"lacks column(s) {missing} (has {table.column_names})")
    wanted = list(columns) + [c for c in optional if c in table.column_names]
    return {c: table.column(c).to_numpy() for c in wanted}


def poses_from_columns(cols: dict[str, np.ndarray], path: Path | str = "") -> np.ndarray:
    """(N,4,4) transforms from AV2's ``qw qx qy qz tx_m ty_m tz_m`` columns (of the file ``path``);
    ``InputError`` for a zero or non-finite quaternion or translation."""
    q = unit_quaternions(np.column_stack([cols["qx"], cols["qy"], cols["qz"], cols["qw"]]), path, "pose table")
    t = np.column_stack([cols["tx_m"], cols["ty_m"], cols["tz_m"]]).astype(np.float64)
    if not np.isfinite(t).all():
        raise InputError(path, "pose table has a non-finite translation")
    return geometry.from_quat_xyzw(q, t)


class Argoverse2Log(Dataset):
    """One AV2 sensor log folder (see module doc for frames, units and flow labels).

    Args:
        path: the log folder holding ``sensors/lidar/``.
        fix_times: repair sweep times that do not increase strictly (two file names of
            the same nanosecond) instead of raising.
    """

    name = "argoverse2"

    def __init__(self, path: str | Path, fix_times: bool = False):
        super().__init__(path)
        if not self.path.exists():
            raise InputError(self.path, "does not exist")
        lidar_dir = self.path / "sensors" / "lidar"
        if not lidar_dir.is_dir():
            raise InputError(self.path, "not an Argoverse 2 log (no sensors/lidar/ folder)")
        files = list(lidar_dir.glob("*.feather"))
        if not files:
            raise InputError(lidar_dir, "no .feather sweeps found")
        bad = [p.name for p in files if not p.stem.isdigit()]
        if bad:
            raise InputError(lidar_dir / bad[0], "sweep file name is not a nanosecond timestamp")
        self.scan_files = sorted(files, key=lambda p: int(p.stem))
        self.timestamps_ns = checked_timestamps(
            np.array([int(p.stem) for p in self.scan_files], dtype=np.int64), lidar_dir, fix=fix_times,
            what="sweep times from the file names (ns)", names=[p.name for p in self.scan_files],
        )
        self.timestamps = self.timestamps_ns * 1e-9
        self.egovehicle_SE3_sensor = self._read_calibration()
        self.gt: ScanPoses | None = None
        self._read_poses()
        self.flow_files = self._find_flow_files()

    def _read_calibration(self) -> dict[str, np.ndarray]:
        path = self.path / "calibration" / "egovehicle_SE3_sensor.feather"
        if not path.exists():
            log.warning("%s: no calibration file", path)
            return {}
        cols = read_feather_columns(path, ("sensor_name",) + POSE_COLUMNS)
        return dict(zip((str(s) for s in cols["sensor_name"]), poses_from_columns(cols, path)))

    def _read_poses(self) -> None:
        path = self.path / "city_SE3_egovehicle.feather"
        if not path.exists():
            log.warning("%s: no ego poses, the log has no GT", path)
            return
        cols = read_feather_columns(path, ("timestamp_ns",) + POSE_COLUMNS)
        stamps = cols["timestamp_ns"].astype(np.int64)
        self.gt = poses_at_scans(stamps, poses_from_columns(cols, path), self.timestamps_ns, str(path))
        self.gt_poses = self.gt.full

    def _find_flow_files(self) -> dict[int, Path]:
        """Sweep index -> flow-label file (see module doc); the last sweep never has one."""
        found: dict[int, Path] = {}
        per_sweep = self.path / "flow_labels"
        for i, sweep in enumerate(self.scan_files[:-1]):
            p = per_sweep / f"{sweep.stem}.feather"
            if p.is_file():
                found[i] = p
        single = self.path / "flow_labels.feather"
        if single.is_file() and 0 not in found and len(self) > 1:
            found[0] = single
        return found

    def __len__(self) -> int:
        return len(self.scan_files)

    def _load(self, index: int) -> Frame:
        path = self.scan_files[index]
        cols = read_feather_columns(path, ("x", "y", "z"), optional=("intensity", "offset_ns", "laser_number"))
        points = np.column_stack([cols[k].astype(np.float64) for k in "xyz"])
        frame = Frame(
            index=index,
            timestamp=float(self.timestamps[index]),
            points=points,
            intensity=cols["intensity"].astype(np.float64) if "intensity" in cols else None,
            point_times=cols["offset_ns"].astype(np.float64) * 1e-9 if "offset_ns" in cols else None,
            gt_pose=None if self.gt is None else self.gt.at(index),
            source=str(path),
            extras={
                "egovehicle_SE3_sensor": self.egovehicle_SE3_sensor,
                "timestamp_ns": int(self.timestamps_ns[index]),
            },
        )
        if "laser_number" in cols:
            frame.extras["laser_number"] = cols["laser_number"]
        if index in self.flow_files:
            self._attach_flow(frame, self.flow_files[index])
        return frame

    def _attach_flow(self, frame: Frame, path: Path) -> None:
        cols = read_feather_columns(path, FLOW_COLUMNS[:3], optional=FLOW_COLUMNS[3:])
        rows = len(cols["flow_tx_m"])
        if rows != len(frame.points):
            raise InputError(path, f"has {rows} flow rows but sweep {frame.source} has {len(frame.points)} points")
        frame.gt_flow = np.column_stack([cols[k].astype(np.float64) for k in FLOW_COLUMNS[:3]])
        if "dynamic" in cols:
            frame.gt_dynamic = cols["dynamic"].astype(bool)
        if "classes" in cols:
            frame.gt_class = cols["classes"].astype(np.int64)
            frame.extras["av2_category"] = frame.gt_class  # already AV2 categories
        if "is_ground_0" in cols:
            frame.extras["is_ground"] = cols["is_ground_0"].astype(bool)
        frame.extras["flow_file"] = str(path)
