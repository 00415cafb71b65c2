"""flowslam.evaluation against evo (GPL-3.0, used here only as a test oracle).

Inputs: the real KITTI 00 GT (first 1000 poses, ~1.1 km with turns) and an
estimate made from it by a seeded random walk of pose noise, expressed in a
different world frame (so alignment matters). All statistics must agree with
evo's ``evo_ape`` / ``evo_rpe`` library functions to 1e-6.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowslam import geometry
from flowslam.evaluation import ape, associate, rpe, rpe_pairs
from flowslam.trajectory import Trajectory, read_trajectory, write_tum

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core.trajectory import PosePath3D, PoseTrajectory3D  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402
from evo.tools import file_interface  # noqa: E402

PR = evo_metrics.PoseRelation
Unit = evo_metrics.Unit
TOL = 1e-6
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")
RELATIONS = {
    "translation": PR.translation_part,
    "rotation_angle_deg": PR.rotation_angle_deg,
    "rotation_angle_rad": PR.rotation_angle_rad,
    "full": PR.full_transformation,
    "rotation_part": PR.rotation_part,
}


def perturbed(poses: np.ndarray, seed: int, sigma_rot=2e-3, sigma_t=0.02, scale=1.0) -> np.ndarray:
    """Random-walk estimate: GT relative motions with noise, chained, in another world frame."""
    rng = np.random.default_rng(seed)
    rel = geometry.inv(poses[:-1]) @ poses[1:]
    # KITTI GT rotations are orthonormal only to ~2e-7 (7 printed digits); chaining
    # 1000 of them would drift off SO(3), so project each step back first.
    rel[:, :3, :3] = Rotation.from_matrix(rel[:, :3, :3]).as_matrix()
    rel[:, :3, 3] *= scale
    noise = rng.normal(0.0, [sigma_rot] * 3 + [sigma_t] * 3, size=(len(rel), 6))
    noisy = np.array([r @ geometry.exp_se3(xi) for r, xi in zip(rel, noise)])
    T_other_world = geometry.from_euler("zyx", [0.7, -0.05, 0.1], t=[12.0, -30.0, 4.0])
    return geometry.compose_relatives(noisy, T_other_world @ poses[0])


@pytest.fixture(scope="module")
def gt_poses(kitti00_full_gt) -> np.ndarray:
    return read_trajectory(kitti00_full_gt).poses[:1000]


@pytest.fixture(scope="module")
def est_poses(gt_poses) -> np.ndarray:
    return perturbed(gt_poses, seed=7)


def _path(poses):
    return PosePath3D(poses_se3=[p.copy() for p in poses])


def _check(ours: dict, result, n: int | None = None):
    stats = result.stats
    for key in STATS:
        assert ours[key] == pytest.approx(stats[key], rel=TOL, abs=TOL), key
    if n is not None:
        assert ours["n"] == n == len(result.np_arrays["error_array"])


@pytest.mark.parametrize("relation", ["translation", "rotation_angle_deg", "full"])
@pytest.mark.parametrize(
    "align,correct_scale", [(False, False), (True, False), (True, True), (False, True)]
)
def test_ape_matches_evo(gt_poses, est_poses, relation, align, correct_scale):
    ours = ape(est_poses, gt_poses, align=align, correct_scale=correct_scale, pose_relation=relation)
    ref = evo_ape(
        _path(gt_poses), _path(est_poses), RELATIONS[relation], align=align, correct_scale=correct_scale
    )
    _check(ours, ref, n=len(gt_poses))
    # The estimate lives in another world frame: aligning must matter (test can fail).
    if relation == "translation" and not align:
        assert ours["rmse"] > 10.0


def test_ape_sim3_recovers_scale(gt_poses):
    est = perturbed(gt_poses, seed=3, sigma_rot=1e-4, sigma_t=1e-3, scale=0.8)
    ours = ape(est, gt_poses, align=True, correct_scale=True)
    ref = evo_ape(_path(gt_poses), _path(est), PR.translation_part, align=True, correct_scale=True)
    _check(ours, ref)
    assert ours["scale"] == pytest.approx(1 / 0.8, rel=1e-2)
    evo_scale = np.cbrt(np.linalg.det(ref.np_arrays["alignment_transformation_sim3"][:3, :3]))
    assert ours["scale"] == pytest.approx(evo_scale, rel=1e-9)


def test_ape_origin_and_first_n_match_evo(gt_poses, est_poses):
    ours = ape(est_poses, gt_poses, align=False, align_origin=True)
    ref = evo_ape(_path(gt_poses), _path(est_poses), PR.translation_part, align_origin=True)
    _check(ours, ref)
    ours = ape(est_poses, gt_poses, align=True, n_to_align=200)
    ref = evo_ape(_path(gt_poses), _path(est_poses), PR.translation_part, align=True, n_to_align=200)
    _check(ours, ref)


@pytest.mark.parametrize("relation", ["translation", "rotation_angle_deg", "rotation_angle_rad", "rotation_part"])
@pytest.mark.parametrize("delta,all_pairs", [(1, False), (5, False), (5, True)])
def test_rpe_frames_match_evo(gt_poses, est_poses, relation, delta, all_pairs):
    ours = rpe(est_poses, gt_poses, delta=delta, delta_unit="frames", all_pairs=all_pairs, pose_relation=relation)
    ref = evo_rpe(
        _path(gt_poses), _path(est_poses), RELATIONS[relation],
        delta=delta, delta_unit=Unit.frames, all_pairs=all_pairs,
    )
    _check(ours, ref)
    expected_pairs = len(gt_poses) - delta if all_pairs else (len(gt_poses) - 1) // delta
    assert ours["n_pairs"] == ours["n"] == expected_pairs


@pytest.mark.parametrize("relation", ["translation", "rotation_angle_deg"])
@pytest.mark.parametrize("all_pairs", [False, True])
@pytest.mark.parametrize("delta_m", [10.0, 37.5])
def test_rpe_metres_match_evo(gt_poses, est_poses, relation, all_pairs, delta_m):
    # Ours takes pairs along the GT path = evo with --pairs_from_reference ...
    ours = rpe(est_poses, gt_poses, delta=delta_m, delta_unit="m", all_pairs=all_pairs, pose_relation=relation)
    ref = evo_rpe(
        _path(gt_poses), _path(est_poses), RELATIONS[relation], delta=delta_m, delta_unit=Unit.meters,
        all_pairs=all_pairs, pairs_from_reference=True,
    )
    _check(ours, ref)
    assert ours["n_pairs"] > 10
    # ... and pairs_from="est" is evo's default.
    ours_est = rpe(est_poses, gt_poses, delta=delta_m, delta_unit="m", all_pairs=all_pairs,
                   pose_relation=relation, pairs_from="est")
    ref_est = evo_rpe(
        _path(gt_poses), _path(est_poses), RELATIONS[relation], delta=delta_m, delta_unit=Unit.meters,
        all_pairs=all_pairs,
    )
    _check(ours_est, ref_est)


def test_rpe_pairs_match_evo_filters(gt_poses):
    from evo.core import filters

    poses = list(gt_poses)
    for delta, all_pairs in [(10.0, False), (10.0, True), (0.85, True), (100.0, False)]:
        ours = rpe_pairs(gt_poses, delta, "m", all_pairs=all_pairs, rel_delta_tol=0.1)
        ref = filters.filter_pairs_by_path(poses, delta, delta * 0.1, all_pairs)
        assert ours.tolist() == [list(p) for p in ref]
    for delta, all_pairs in [(1, False), (7, False), (7, True)]:
        ours = rpe_pairs(gt_poses, delta, "frames", all_pairs=all_pairs)
        assert ours.tolist() == [list(p) for p in filters.filter_pairs_by_index(poses, delta, all_pairs)]


def test_rpe_with_scale_correction_matches_evo(gt_poses):
    est = perturbed(gt_poses, seed=11, scale=1.1)
    ours = rpe(est, gt_poses, delta=5, correct_scale=True, align=True)
    ref = evo_rpe(_path(gt_poses), _path(est), PR.translation_part, delta=5, delta_unit=Unit.frames,
                  align=True, correct_scale=True)
    _check(ours, ref)


# --- TUM files with timestamps that need association -------------------------------


@pytest.fixture(scope="module")
def tum_pair(tmp_path_factory, gt_poses, est_poses, kitti00_full_gt):
    """GT at the real KITTI stamps; estimate at jittered stamps shifted by +100 s, every
    pose but a few dropped, and 50 extra GT-less poses at the end."""
    d = tmp_path_factory.mktemp("tum")
    stamps = np.loadtxt(kitti00_full_gt.with_name("kitti00_gt_times.txt"))[: len(gt_poses)]
    rng = np.random.default_rng(5)
    keep = np.sort(rng.choice(len(gt_poses), size=900, replace=False))
    est_stamps = stamps[keep] + 100.0 + rng.uniform(-0.004, 0.004, size=len(keep))
    extra_t = est_stamps[-1] + 0.1 * np.arange(1, 51) + 30.0
    extra = np.repeat(est_poses[-1:], 50, axis=0)
    gt_file, est_file = d / "gt.tum", d / "est.tum"
    write_tum(gt_file, Trajectory(gt_poses, stamps))
    write_tum(est_file, Trajectory(np.concatenate([est_poses[keep], extra]), np.concatenate([est_stamps, extra_t])))
    return gt_file, est_file


@pytest.mark.parametrize("max_diff", [0.01, 0.003])
def test_tum_association_and_metrics_match_evo(tum_pair, max_diff):
    gt_file, est_file = tum_pair
    gt, est = read_trajectory(gt_file), read_trajectory(est_file)
    est_m, gt_m = associate(est, gt, max_diff=max_diff, offset=-100.0)

    ref_gt = file_interface.read_tum_trajectory_file(gt_file)
    ref_est = file_interface.read_tum_trajectory_file(est_file)
    ref_gt, ref_est = ref_gt.sync_with(ref_est, max_diff=max_diff, offset_2=-100.0)
    assert isinstance(ref_est, PoseTrajectory3D)
    np.testing.assert_array_equal(est_m.timestamps, ref_est.timestamps)
    np.testing.assert_array_equal(gt_m.timestamps, ref_gt.timestamps)
    if max_diff == 0.01:
        assert len(est_m) == 900  # every kept pose pairs; the 50 extras do not
    else:
        assert 400 < len(est_m) < 900  # tighter window drops the most jittered ones

    _check(ape(est_m, gt_m, align=True), evo_ape(copy.deepcopy(ref_gt), copy.deepcopy(ref_est),
                                               PR.translation_part, align=True))
    _check(
        rpe(est_m, gt_m, delta=1, pose_relation="rotation_angle_deg"),
        evo_rpe(copy.deepcopy(ref_gt), copy.deepcopy(ref_est), PR.rotation_angle_deg, delta=1,
                delta_unit=Unit.frames),
    )


def test_association_needs_the_offset(tum_pair):
    gt_file, est_file = tum_pair
    gt, est = read_trajectory(gt_file), read_trajectory(est_file)
    from flowslam.errors import InputError

    with pytest.raises(InputError, match="no timestamps"):
        associate(est, gt)  # 100 s apart: nothing within 10 ms


def test_association_matches_evo_when_gt_is_shorter(gt_poses, est_poses):
    """Walk direction flips when the GT has fewer poses; offsets must still apply to the estimate."""
    rng = np.random.default_rng(2)
    t_gt = np.arange(0, 300) * 0.1 + 0.02
    t_est = np.arange(0, 1000) * 0.03 - 1.0 + rng.uniform(-1e-3, 1e-3, 1000)
    gt = Trajectory(gt_poses[:300], t_gt)
    est = Trajectory(est_poses, t_est)
    est_m, gt_m = associate(est, gt, max_diff=0.01, offset=0.5)
    ref_gt, ref_est = PoseTrajectory3D(poses_se3=list(gt.poses), timestamps=t_gt.copy()).sync_with(
        PoseTrajectory3D(poses_se3=list(est.poses), timestamps=t_est.copy()), max_diff=0.01, offset_2=0.5
    )
    assert len(est_m) > 50
    np.testing.assert_array_equal(est_m.timestamps, ref_est.timestamps)
    np.testing.assert_array_equal(gt_m.timestamps, ref_gt.timestamps)
