"""Map files: ``static_map.ply`` / ``.pcd`` with intensity and ``dynamic_points.ply`` with
instance ids, written with Open3D's tensor IO and read back with it.

A world scene seen from two poses checks the coordinates and the intensities; a short
simulated ``dt`` sequence through the ``gt`` frontend checks the dynamic points against
the simulator's labels (every removed point is in ``dynamic_points.ply`` with its
instance id, none is in the static map)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flowslam import geometry
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput
from flowslam.mapping import DynamicPoints, MapCloud, StaticMapBuilder, write_point_cloud

from test_flow_odometry import street_scene

o3d = pytest.importorskip("open3d")


def _read(path: Path) -> dict[str, np.ndarray]:
    """Every attribute of a point cloud file, by Open3D's tensor reader, as numpy arrays."""
    cloud = o3d.t.io.read_point_cloud(str(path))
    return {name: cloud.point[name].numpy() for name in cloud.point}


def _intensity_of(points_world: np.ndarray) -> np.ndarray:
    """A smooth intensity field over the world (0.1..0.9), so a point's value says where it was."""
    return 0.5 + 0.4 * np.sin(points_world[:, 0] / 7.0) * np.cos(points_world[:, 1] / 5.0)


def test_static_map_ply_and_pcd_hold_world_points_with_their_intensity(tmp_path: Path):
    rng = np.random.default_rng(0)
    world = street_scene(rng, 40000)
    poses = {3: geometry.from_euler("z", 10.0, t=[2.0, -1.0, 0.1], degrees=True),
             4: geometry.from_euler("zyx", [25.0, 1.0, -0.5], t=[6.0, 1.5, 0.2], degrees=True)}
    builder = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10**6)
    for index, T in poses.items():
        builder.add(index, geometry.transform_points(geometry.inv(T), world), None, _intensity_of(world))
    n = builder.write(tmp_path / "static_map.ply", poses)
    assert builder.write(tmp_path / "static_map.pcd", poses) == n > 10000

    for name in ("static_map.ply", "static_map.pcd"):
        read = _read(tmp_path / name)
        assert set(read) == {"positions", "intensity"} and read["intensity"].dtype == np.float32
        positions, intensity = read["positions"].astype(np.float64), read["intensity"][:, 0]
        assert len(positions) == len(intensity) == n
        assert 0.1 - 1e-3 <= intensity.min() and intensity.max() <= 0.9 + 1e-3  # within the input range
        d, _ = cKDTree(world).query(positions)
        assert np.percentile(d, 99) < 0.2  # on the scene: the poses placed both scans right
        # each voxel's intensity is the mean of its points': the field at the centroid
        assert np.median(np.abs(intensity - _intensity_of(positions))) < 5e-3
    ply, pcd = _read(tmp_path / "static_map.ply"), _read(tmp_path / "static_map.pcd")
    np.testing.assert_array_equal(ply["positions"], pcd["positions"])  # the same map, built once
    # the wrong pose for one scan puts its half of the map off the scene
    wrong = builder.build({3: poses[3], 4: poses[3]})
    assert np.percentile(cKDTree(world).query(wrong)[0], 90) > 0.3


def test_scans_without_intensity_write_zero():
    builder = StaticMapBuilder(voxel_size=0.5)
    frame = Frame(index=0, timestamp=0.0, points=np.random.default_rng(1).uniform(-9, 9, (800, 3)))
    builder.on_output(frame, FrontendOutput(index=0, T_prev_curr=None))
    cloud = builder.cloud({0: np.eye(4)})
    assert len(cloud) > 100 and not cloud.intensity.any()


def test_per_scan_storage_costs_8_and_12_bytes_a_point():
    pts = np.random.default_rng(2).uniform(-40, 40, (50000, 3))
    builder = StaticMapBuilder(voxel_size=0.1, max_points_per_frame=2000)
    builder.add(0, pts, None, np.full(len(pts), 70000.0))  # beyond float16: clipped
    scan = builder.store.scans[0]
    assert len(scan.points) == 2000 and scan.points.nbytes + scan.intensity.nbytes == 2000 * 8
    assert scan.intensity.max() == np.float16(65504)
    dynamic = DynamicPoints(voxel_size=0.1, max_points_per_frame=2000)
    dynamic.add(0, pts, None, np.arange(len(pts)) % 5)
    d = dynamic.store.scans[0]
    assert len(d.points) == 2000 and d.points.nbytes + d.intensity.nbytes + d.instance.nbytes == 2000 * 12
    assert set(np.unique(d.instance)) == set(range(5))


def test_a_file_size_limit_is_an_oserror_naming_the_reason(tmp_path: Path):
    """Open3D's PLY writer says True for a file cut at RLIMIT_FSIZE (and prints a line per
    lost value); the writer claims the space first, so the OS names the reason."""
    code = f"""
import resource, signal, numpy as np
from flowslam.mapping import MapCloud, write_point_cloud
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))
cloud = MapCloud(np.random.default_rng(0).uniform(-9, 9, (100000, 3)), np.zeros(100000, np.float32))
for suffix in ("ply", "pcd"):
    try:
        write_point_cloud("{tmp_path}/map." + suffix, cloud)
        print("written")
    except OSError as e:
        print(e.strerror)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["File", "too", "large"] * 2 and "RPly" not in proc.stderr


# --------------------------------------------------------------------- simulated traffic


@pytest.fixture(scope="module")
def dt_run(tmp_path_factory):
    """A 6-frame simulated ``dt`` sequence through ``gt`` + ``odometry``, the maps collected."""
    from flowslam.config import load_config
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend
    from flowslam.simulation import simulate

    seq = tmp_path_factory.mktemp("sim") / "dt"
    simulate(seq, preset="dt", frames=6, seed=4, sensor="vlp32c", columns=720)
    dataset = open_dataset(seq)
    config = load_config()
    builder = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10000)
    result = run_pipeline(dataset, make_frontend("gt", config), make_backend("odometry", config),
                          on_output=builder.on_output)
    assert result.error is None and result.indices == list(range(6))
    return dataset, result, builder


def test_dynamic_points_are_the_removed_points_with_instance_ids(dt_run, tmp_path: Path):
    dataset, result, builder = dt_run
    assert builder.removes_dynamic
    n = builder.dynamic.write(tmp_path / "dynamic_points.ply", result.poses, result.indices)
    read = _read(tmp_path / "dynamic_points.ply")
    assert set(read) == {"positions", "intensity", "instance", "frame"} and len(read["positions"]) == n > 1000
    frame, instance = read["frame"][:, 0], read["instance"][:, 0]
    assert sorted(set(frame)) == [0, 1, 2, 3, 4]  # scan 5 (the last) never gets its flow
    for k in range(5):
        f = dataset[k]
        moving = f.gt_dynamic
        mine = frame == k
        # every moving instance of the scan is there, nothing else
        assert set(instance[mine]) == set(f.gt_instance[moving])
        # each written point is a moving point of scan k (1 cm storage), same id, same intensity
        gt_world = geometry.transform_points(result.poses[k], f.points[moving])
        d, nearest = cKDTree(gt_world).query(read["positions"][mine].astype(np.float64))
        assert d.max() < 0.01
        np.testing.assert_array_equal(instance[mine], f.gt_instance[moving][nearest])
        np.testing.assert_allclose(read["intensity"][mine, 0], f.intensity[moving][nearest], rtol=1e-3, atol=1e-4)
        assert np.count_nonzero(mine) >= 0.3 * np.count_nonzero(moving)  # one per 0.2 m voxel and instance


def test_no_removed_point_is_in_the_static_map(dt_run, tmp_path: Path):
    dataset, result, builder = dt_run
    builder.write(tmp_path / "static_map.pcd", result.poses, result.indices)
    static_map = _read(tmp_path / "static_map.pcd")["positions"].astype(np.float64)
    scans = [dataset[k] for k in range(5)]
    world = [geometry.transform_points(result.poses[k], f.points) for k, f in enumerate(scans)]
    static_world = np.vstack([w[~f.gt_dynamic] for w, f in zip(world, scans)])
    moving_world = np.vstack([w[f.gt_dynamic] for w, f in zip(world, scans)])
    # moving points away from any static surface (car bodies, not wheels on the road)
    clear = moving_world[cKDTree(static_world).query(moving_world)[0] > 0.5]
    assert len(clear) > 500
    assert cKDTree(static_map).query(clear)[0].min() > 0.15  # no static-map point where they were
    # without the removal they would be in the map
    everything = StaticMapBuilder(voxel_size=0.2, max_points_per_frame=10000)
    for k, f in enumerate(scans):
        everything.add(k, f.points, None, f.intensity)
    assert np.median(cKDTree(everything.build(result.poses[:5], range(5))).query(clear)[0]) < 0.15
    # the static map's intensity is the readers' (within the input range)
    intensity = _read(tmp_path / "static_map.pcd")["intensity"]
    lo, hi = min(f.intensity.min() for f in scans), max(f.intensity.max() for f in scans)
    assert lo - 1e-3 <= intensity.min() and intensity.max() <= hi + 1e-3


def test_a_frontend_without_segmentation_gives_no_dynamic_points():
    builder = StaticMapBuilder(voxel_size=0.2)
    pts = np.random.default_rng(5).uniform(-9, 9, (500, 3))
    for k in range(3):
        frame = Frame(index=k, timestamp=0.1 * k, points=pts)
        builder.on_output(frame, FrontendOutput(index=k, T_prev_curr=None if k == 0 else np.eye(4),
                                                points=None if k == 0 else pts))
    assert not builder.removes_dynamic and builder.dynamic.n_points == 0 and builder.n_points > 0


def test_map_cloud_labels_are_written_as_int32(tmp_path: Path):
    cloud = MapCloud(np.zeros((3, 3)) + np.arange(3)[:, None], np.ones(3, np.float32),
                     {"instance": np.array([-1, 4, 2**20])})
    read = _read(write_point_cloud(tmp_path / "c.ply", cloud))
    assert read["instance"].dtype == np.int32 and read["instance"][:, 0].tolist() == [-1, 4, 2**20]
