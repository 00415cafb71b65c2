"""Argoverse2Log on the real AV2 validation log (2 sweeps + flow labels + 200 Hz ego poses).

Key check: the log's own ego poses, interpolated to the sweep timestamps, reproduce
the flow labels of the static points (flow = T_ego1_ego0 p - p).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from scipy.spatial.transform import Rotation, Slerp

from flowslam import geometry
from flowslam.datasets.argoverse2 import Argoverse2Log
from flowslam.errors import InputError

log = logging.getLogger(__name__)

SWEEPS = (315966265259836000, 315966265360032000)


@pytest.fixture(scope="module")
def av2(av2_log: Path) -> Argoverse2Log:
    return Argoverse2Log(av2_log)


@pytest.fixture(scope="module")
def frame0(av2: Argoverse2Log):
    return av2[0]


def test_sweeps_points_and_times(av2: Argoverse2Log, frame0):
    assert len(av2) == 2
    np.testing.assert_array_equal(av2.timestamps_ns, SWEEPS)
    assert av2.timestamps[1] - av2.timestamps[0] == pytest.approx(0.1002, abs=1e-4)
    frame1 = av2[1]
    assert (len(frame0), len(frame1)) == (99229, 99466)
    raw = feather.read_table(av2.scan_files[0]).to_pydict()
    np.testing.assert_array_equal(frame0.points[:, 0], np.array(raw["x"], dtype=np.float64))
    np.testing.assert_array_equal(frame0.intensity, np.array(raw["intensity"], dtype=np.float64))
    assert frame0.point_times.min() >= 0.0 and frame0.point_times.max() < 0.11
    np.testing.assert_allclose(frame0.point_times, np.array(raw["offset_ns"]) * 1e-9)
    assert len(frame0.extras["laser_number"]) == len(frame0)
    assert {"up_lidar", "down_lidar"} <= set(frame0.extras["egovehicle_SE3_sensor"])
    assert geometry.is_se3(av2.egovehicle_SE3_sensor["up_lidar"])
    assert frame1.gt_flow is None and frame1.gt_dynamic is None  # the last sweep has no successor


def test_flow_labels_on_frame0(frame0):
    assert frame0.gt_flow.shape == (99229, 3) and frame0.gt_flow.dtype == np.float64
    assert frame0.gt_dynamic.dtype == bool and frame0.gt_dynamic.sum() == 2037
    assert frame0.gt_class.shape == (99229,)
    assert frame0.extras["is_ground"].dtype == bool and 0 < frame0.extras["is_ground"].sum() < len(frame0)


def test_gt_poses_exact_at_sweep_stamps(av2: Argoverse2Log, av2_log: Path):
    table = feather.read_table(av2_log / "city_SE3_egovehicle.feather").to_pydict()
    stamps = np.array(table["timestamp_ns"])
    for k, ts in enumerate(SWEEPS):
        row = int(np.flatnonzero(stamps == ts)[0])
        q = [table["qx"][row], table["qy"][row], table["qz"][row], table["qw"][row]]
        t = [table["tx_m"][row], table["ty_m"][row], table["tz_m"][row]]
        np.testing.assert_allclose(av2.gt_poses[k], geometry.from_quat_xyzw(np.array(q) / np.linalg.norm(q), t),
                                   rtol=0, atol=1e-12)
    assert av2.gt.valid.all()


def test_static_flow_reproduced_by_ego_poses(av2: Argoverse2Log, frame0, av2_log: Path):
    """flow = T_ego1_ego0 p - p for static points, with T_ego1_ego0 = inv(T_city_ego1) @ T_city_ego0."""
    T_1_0 = geometry.relative(av2.gt_poses[1], av2.gt_poses[0])
    p = frame0.points
    err = np.linalg.norm(geometry.transform_points(T_1_0, p) - p - frame0.gt_flow, axis=1)
    static = ~frame0.gt_dynamic
    background = static & (frame0.gt_class == 0)
    on_objects = static & (frame0.gt_class != 0)
    for name, m in (("static", static), ("static background", background), ("static on objects", on_objects)):
        log.info("%s (%d pts): max %.5f m, median %.6f m, p99 %.5f m", name, m.sum(), err[m].max(),
                 np.median(err[m]), np.percentile(err[m], 99))
    # background points: pure ego motion (the 0.8 mm is the labels' float16-rounded ego translation)
    assert np.median(err[background]) < 1e-3 and err[background].max() < 2e-3
    # static points inside annotated boxes carry their box's (sub-threshold) motion: AV2 calls a point
    # dynamic above 0.05 m per 0.1 s of residual motion, so static residuals stay below that
    assert np.median(err[static]) < 1e-3 and np.percentile(err[static], 99) < 0.025
    assert err[static].max() < 0.05 + 2e-3
    assert np.median(err[frame0.gt_dynamic]) > 0.1  # the dynamic points really move

    # the log's own ego_motion.npz (T_1<-0, float32 with float16-rounded translation) agrees
    T_npz = np.load(av2_log / "ego_motion.npz")["ego_motion"][0].astype(np.float64)
    np.testing.assert_allclose(T_npz[:3, :3], T_1_0[:3, :3], rtol=0, atol=2e-6)
    np.testing.assert_allclose(T_npz[:3, 3], T_1_0[:3, 3], rtol=0, atol=1e-3)
    err_npz = np.linalg.norm(geometry.transform_points(T_npz, p) - p - frame0.gt_flow, axis=1)
    assert err_npz[background].max() < 1e-4


def _log_copy(src: Path, dst: Path, sweep_names: dict[int, int] | None = None) -> Path:
    """A log folder with symlinked sweeps (optionally renamed to other timestamps) and poses/calib."""
    (dst / "sensors" / "lidar").mkdir(parents=True)
    for ts in SWEEPS:
        new = (sweep_names or {}).get(ts, ts)
        (dst / "sensors" / "lidar" / f"{new}.feather").symlink_to(src / "sensors" / "lidar" / f"{ts}.feather")
    (dst / "city_SE3_egovehicle.feather").symlink_to(src / "city_SE3_egovehicle.feather")
    (dst / "calibration").symlink_to(src / "calibration")
    return dst


def test_pose_interpolated_between_samples(av2_log: Path, tmp_path: Path):
    table = feather.read_table(av2_log / "city_SE3_egovehicle.feather").to_pydict()
    stamps = np.array(table["timestamp_ns"])
    row = int(np.flatnonzero(stamps == SWEEPS[1])[0])
    query = int(stamps[row] + 0.37 * (stamps[row + 1] - stamps[row]))
    ds = Argoverse2Log(_log_copy(av2_log, tmp_path, {SWEEPS[1]: query}))
    quats = np.array([[table[k][r] for k in ("qx", "qy", "qz", "qw")] for r in (row, row + 1)])
    rot = Slerp([0.0, 1.0], Rotation.from_quat(quats))([0.37])[0].as_matrix()
    t = np.array([[table[k][r] for k in ("tx_m", "ty_m", "tz_m")] for r in (row, row + 1)])
    alpha = (query - stamps[row]) / (stamps[row + 1] - stamps[row])
    np.testing.assert_allclose(ds.gt_poses[1][:3, :3], rot, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ds.gt_poses[1][:3, 3], t[0] + alpha * (t[1] - t[0]), rtol=0, atol=1e-9)
    assert not ds.flow_files  # no labels in this copy


def test_flow_rows_mismatch(av2_log: Path, tmp_path: Path):
    log_dir = _log_copy(av2_log, tmp_path)
    flow = feather.read_table(av2_log / "flow_labels.feather")
    feather.write_feather(flow.slice(0, flow.num_rows - 10), log_dir / "flow_labels.feather")
    ds = Argoverse2Log(log_dir)
    with pytest.raises(InputError) as err:
        ds[0]
    assert err.value.where == str(log_dir / "flow_labels.feather")
    assert f"has 99219 flow rows but sweep {ds.scan_files[0]} has 99229 points" in err.value.problem
    assert len(ds[1]) == 99466  # the other sweep still loads


def test_per_sweep_flow_folder_and_missing_columns(av2_log: Path, tmp_path: Path):
    log_dir = _log_copy(av2_log, tmp_path)
    (log_dir / "flow_labels").mkdir()
    (log_dir / "flow_labels" / f"{SWEEPS[0]}.feather").symlink_to(av2_log / "flow_labels.feather")
    ds = Argoverse2Log(log_dir)
    assert ds[0].gt_dynamic.sum() == 2037
    feather.write_feather(pa.table({"flow_tx_m": [0.0]}), log_dir / "flow_labels.feather")
    (log_dir / "flow_labels" / f"{SWEEPS[0]}.feather").unlink()
    with pytest.raises(InputError, match=r"flow_labels\.feather: lacks column\(s\) \['flow_ty_m', 'flow_tz_m'\]"):
        Argoverse2Log(log_dir)[0]


def test_bad_logs(tmp_path: Path):
    with pytest.raises(InputError, match="does not exist"):
        Argoverse2Log(tmp_path / "nope")
    with pytest.raises(InputError, match=r"not an Argoverse 2 log \(no sensors/lidar/ folder\)"):
        Argoverse2Log(tmp_path)
    (tmp_path / "sensors" / "lidar").mkdir(parents=True)
    with pytest.raises(InputError, match="no .feather sweeps found"):
        Argoverse2Log(tmp_path)
    (tmp_path / "sensors" / "lidar" / "123.feather").write_bytes(b"garbage")
    ds = Argoverse2Log(tmp_path)
    assert ds.gt_poses is None
    with pytest.raises(InputError, match=r"123\.feather: not a readable feather file"):
        ds[0]
