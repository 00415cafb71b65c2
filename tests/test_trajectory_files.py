"""TUM / KITTI trajectory files: round trips and malformed files."""

import numpy as np
import pytest

from flowslam import geometry as g
from flowslam.errors import InputError
from flowslam.trajectory import Trajectory, read_trajectory, write_kitti, write_tum


def _traj(n=20):
    rng = np.random.default_rng(3)
    poses = np.stack([g.exp_se3(rng.normal(size=6)) for _ in range(n)])
    return Trajectory(poses, 1e9 + np.arange(n) * 0.1)


def test_tum_and_kitti_roundtrip(tmp_path):
    traj = _traj()
    write_tum(tmp_path / "t.txt", traj)
    write_kitti(tmp_path / "k.txt", traj)
    tum, kitti = read_trajectory(tmp_path / "t.txt"), read_trajectory(tmp_path / "k.txt")
    np.testing.assert_allclose(tum.poses, traj.poses, atol=1e-8)
    np.testing.assert_allclose(tum.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(kitti.poses, traj.poses, atol=1e-8)
    assert kitti.timestamps is None


def test_real_kitti_poses_file(kitti_extract):
    traj = read_trajectory(kitti_extract / "poses" / "00.txt")
    assert len(traj) == 16
    assert traj.path_length() == pytest.approx(12.9, abs=0.1)


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "holds no poses"),
        ("1 2 3\n", "3 columns"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n", "different lengths"),
        ("a b c d e f g h\n", "non-numeric"),
        ("0 0 0 0 0 0 0 0\n", "zero quaternion"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", "not a rigid transform"),
    ],
)
def test_malformed_files_name_file_and_problem(tmp_path, content, message):
    path = tmp_path / "poses.txt"
    path.write_text(content)
    with pytest.raises(InputError) as info:
        read_trajectory(path)
    assert str(path) in str(info.value) and message in str(info.value)


def test_missing_and_binary_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_trajectory(tmp_path / "nope.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(InputError, match="cannot read"):
        read_trajectory(tmp_path / "bin.txt")
