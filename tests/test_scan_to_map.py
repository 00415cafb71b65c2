"""The mapping stage (flowslam/scan_to_map.py): scan-to-map factors correct a drifting
odometry, mapping off is the plain odometry graph, the factors are marked in graph.g2o.

A simulated ``dt`` sequence (exact GT poses) through the ``gt`` frontend with a known
bias injected into every step: 0.3 deg of yaw and 2 cm forward per scan, declared with a
covariance of 0.2 deg / 5 cm. The map sees the true geometry, so its factors must pull the
poses back to the truth that the chained odometry leaves behind.
"""

from __future__ import annotations

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config import load_config

BIAS = geometry.make_T(geometry.from_euler("z", 0.3, degrees=True)[:3, :3], [0.02, 0.0, 0.0])
"""Injected into every odometry step (T_prev_curr @ BIAS)."""


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from flowslam.datasets import open_dataset
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "dt30"
    simulate(out, preset="dt", frames=30, seed=5, sensor="hdl64", columns=360)
    dataset = open_dataset(out)
    gt = np.array([dataset[k].gt_pose for k in range(len(dataset))])
    return dataset, np.linalg.inv(gt[0]) @ gt


class BiasedGt:
    """The ``gt`` frontend with :data:`BIAS` in every step (a drifting odometry)."""

    name = "gt-biased"

    def __init__(self, config):
        from flowslam.registry import make_frontend

        self.inner = make_frontend("gt", config)

    def process(self, frame):
        out = self.inner.process(frame)
        if out.T_prev_curr is not None:
            out.T_prev_curr = out.T_prev_curr @ BIAS
            out.covariance = geometry.pose_covariance(np.deg2rad(0.2), 0.05)
        return out


def _config(mapping: bool):
    return load_config(backend="isam2", variant="a-loam", **{"mapping.enabled": mapping})


def _run(dataset, config):
    from flowslam.pipeline import drive
    from flowslam.slam import Slam

    slam = Slam(config, frontend=BiasedGt(config), outputs=False)
    result = drive(slam, dataset, range(len(dataset)), None)
    assert result.error is None
    return slam


def _errors(poses, gt):
    """Largest position (m) and rotation (deg) error over the sequence."""
    trans = [np.linalg.norm(P[:3, 3] - G[:3, 3]) for P, G in zip(poses, gt)]
    rot = [np.rad2deg(np.linalg.norm(geometry.log_se3(geometry.inv(P) @ G)[:3])) for P, G in zip(poses, gt)]
    return max(trans), max(rot)


def test_map_factors_undo_an_injected_drift(sequence, tmp_path):
    dataset, gt = sequence
    off = _run(dataset, _config(False))
    on = _run(dataset, _config(True))
    t_off, r_off = _errors(off.trajectory().poses, gt)
    t_on, r_on = _errors(on.trajectory().poses, gt)
    # 29 steps of 0.3 deg: the chain ends ~8.7 deg and more than a metre off
    assert r_off > 8.0 and t_off > 1.0, (t_off, r_off)
    assert r_on < 1.5 and t_on < 0.3, (t_on, r_on)
    stats = on.describe()["mapping"]
    assert stats["factors"] >= len(dataset) - 1 - on.config.mapping.warmup_scans - 1 and stats["restarts"] == 0
    assert on.backend.stats["map_factors"] == stats["factors"]
    # graph.g2o marks them; an odometry edge and a map edge may join the same two scans
    path = on.backend.write_g2o(tmp_path / "graph.g2o")
    kinds = [line.split()[2] for line in path.read_text().splitlines() if line.startswith("# FLOWSLAM_EDGE")]
    assert kinds.count("map") == stats["factors"] and kinds.count("odometry") == len(dataset) - 1


def test_mapping_off_is_the_odometry_graph(sequence):
    """Without the stage the graph holds the odometry alone: the trajectory is the chain."""
    dataset, _ = sequence
    off = _run(dataset, _config(False))
    assert off.scan_to_map is None and off.describe()["mapping"] is None
    assert off.backend.stats["map_factors"] == 0
    chain = geometry.compose_relatives(off.result().odometry)
    np.testing.assert_allclose(off.trajectory().poses, chain, atol=1e-9)


def test_mapping_needs_a_graph_backend(kitti_extract, tmp_path):
    """Asked for with a backend without factors: one line, exit 2; from the config alone
    (not asked for on the command line) the stage is simply not built."""
    from cli_helpers import assert_one_line_error, flowslam

    from flowslam.slam import Slam

    proc = flowslam("run", "-f", "kiss-icp", "-b", "odometry", "--mapping", "--no-progress",
                    "-o", tmp_path / "results", kitti_extract)
    assert_one_line_error(proc, "--mapping: backend 'odometry' takes no map factors")
    assert not (tmp_path / "results").exists()
    slam = Slam(load_config(backend="odometry", **{"mapping.enabled": True}))
    assert slam.scan_to_map is None and slam.describe()["mapping"] is None


def test_a_moved_backend_carries_the_map(sequence):
    """After a loop closure moves the poses, the map and its anchor move with the latest
    pose: the next scan's factor is the true relative pose, with or without the move
    (the voxel grid is not rigid-invariant, so the two differ by millimetres)."""
    from flowslam.config import MappingConfig
    from flowslam.scan_to_map import ScanToMap

    dataset, gt = sequence
    C = geometry.make_T(geometry.from_euler("z", 5.0, degrees=True)[:3, :3], [3.0, -2.0, 0.1])
    factors = []
    for move in (False, True):
        stage = ScanToMap(MappingConfig(enabled=True))
        poses = {k: gt[k] for k in range(6)}
        for k in range(5):
            stage.step(k, dataset[k].points, None, poses.__getitem__)
        if move:
            stage.moved(poses[4], C @ poses[4])
            poses = {k: C @ P for k, P in poses.items()}
        factors.append(stage.step(5, dataset[5].points, None, poses.__getitem__))
    assert factors[0] is not None and factors[1] is not None
    assert factors[0].anchor == factors[1].anchor
    T_true = geometry.relative(gt[factors[0].anchor], gt[5])
    for factor in factors:
        xi = geometry.log_se3(geometry.inv(T_true) @ factor.T_anchor_scan)
        assert np.linalg.norm(xi[3:]) < 0.02 and np.rad2deg(np.linalg.norm(xi[:3])) < 0.1, xi


def test_a_replayed_recording_maps_like_the_run(sequence):
    """``flowslam demo`` / ``bench`` replay a frontend's recording into isam2: with the
    static masks recorded (the points themselves are taken from the replayed frames) the
    mapping stage sees what it sees in a direct run, and the trajectories agree."""
    from flowslam.pipeline import drive
    from flowslam.registry import make_frontend
    from flowslam.replay import RecordingFrontend, ReplayFrontend
    from flowslam.slam import Slam

    dataset, _ = sequence
    frames = range(12)
    config = _config(True)
    direct = Slam(config, frontend=make_frontend("gt", config), outputs=False)
    assert drive(direct, dataset, frames, None).error is None
    recorder = RecordingFrontend(make_frontend("gt", config), per_point=True)
    first = Slam(load_config(backend="odometry"), frontend=recorder, outputs=False)
    assert drive(first, dataset, frames, None).error is None
    assert recorder.points_from_previous == set(frames[1:])  # gt hands back the previous scan's own array
    assert all(recorder.records[k].points is None and recorder.records[k].static_mask is not None for k in frames[1:])
    replayed = Slam(config, frontend=ReplayFrontend.of(recorder), outputs=False)
    assert drive(replayed, dataset, frames, None).error is None
    assert replayed.describe()["mapping"]["factors"] == direct.describe()["mapping"]["factors"] > 0
    np.testing.assert_allclose(replayed.trajectory().poses, direct.trajectory().poses, atol=1e-9)


def test_registration_to_the_map_equals_open3d(kitti_extract):
    """The compiled point-to-plane registration onto the local map (its KD-tree kept while
    the map is unchanged) lands a real KITTI scan where Open3D's ``registration_icp`` with
    the same kernel and criteria does (1e-9 m), for a second call on the same map too."""
    import open3d as o3d

    from flowslam.config import MappingConfig
    from flowslam.datasets import open_dataset
    from flowslam.scan_to_map import ScanToMap

    c = MappingConfig()
    ds = open_dataset(kitti_extract)
    stm = ScanToMap(c)
    for k in range(4):  # four scans in the map at their GT poses
        stm._insert(stm._prepare(ds[k].points, None), ds[k].gt_pose, k, into_map=True)
    reg = o3d.pipelines.registration
    for k, offset in ((4, 0.0), (5, 0.4)):
        cloud = stm._prepare(ds[k].points, None)
        guess = geometry.from_euler("z", 0.01, t=[offset, 0.0, 0.0]) @ ds[k].gt_pose
        ours = stm._register(cloud, guess)
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud)).voxel_down_sample(c.source_voxel_m)
        map_points, map_normals = stm.map.cloud()
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(map_points))
        target.normals = o3d.utility.Vector3dVector(map_normals)
        theirs = reg.registration_icp(
            source, target, c.max_correspondence_m, guess,
            reg.TransformationEstimationPointToPlane(reg.TukeyLoss(c.kernel_m)),
            reg.ICPConvergenceCriteria(relative_fitness=1e-4, relative_rmse=1e-4, max_iteration=c.max_iterations))
        p = np.asarray(source.points)  # (their order; the same voxel means as ours)
        np.testing.assert_allclose(geometry.transform_points(ours, p),
                                   geometry.transform_points(geometry.orthonormalized(np.asarray(theirs.transformation)), p),
                                   atol=1e-9)
