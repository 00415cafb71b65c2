"""Typed config (YAML round trip, validation) and the frontend/backend registry."""

import numpy as np
import pytest

from flowslam.config import dump_config, load_config
from flowslam.errors import InputError
from flowslam.registry import (
    backend_names, frontend_names, make_backend, make_frontend, register_backend,
)


def test_defaults_dump_and_reload(tmp_path):
    cfg = load_config()
    assert (cfg.frontend, cfg.backend) == ("kiss-icp", "odometry")
    path = tmp_path / "c.yaml"
    path.write_text(dump_config(cfg).replace("max_range: 100.0", "max_range: 50.0"))
    again = load_config(path, frontend="kiss-icp", **{"dataset.max_frames": 5})
    assert again.kiss_icp.max_range == 50.0 and again.dataset.max_frames == 5


@pytest.mark.parametrize(
    "text, message", [("kiss_icp: {max_rang: 3}", "max_rang"), ("- a\n- b", "YAML mapping"),
                      ("kiss_icp: {max_range: far}", "max_range")],
)
def test_bad_config_is_input_error(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_config(path)


def test_unknown_names_list_the_choices():
    with pytest.raises(InputError, match="unknown frontend 'nope'.*kiss-icp"):
        make_frontend("nope", load_config())
    with pytest.raises(InputError, match="unknown backend 'nope'.*odometry"):
        make_backend("nope", load_config())


def test_library_user_registers_a_backend():
    class Recorder:
        name = "recorder-test"

        def __init__(self):
            self.calls = []

        def add_odometry(self, index, T, cov):
            self.calls.append(index)

        def add_loop(self, i, j, T, cov):
            pass

        def trajectory(self):
            return np.zeros((len(self.calls), 4, 4))

        def latest_pose(self):
            return np.eye(4)

    register_backend("recorder-test", lambda config: Recorder())
    assert "recorder-test" in backend_names() and "kiss-icp" in frontend_names()
    backend = make_backend("recorder-test", load_config())
    backend.add_odometry(0, None, None)
    assert backend.calls == [0]
    with pytest.raises(ValueError, match="already registered"):
        register_backend("recorder-test", lambda config: None)


def test_odometry_backend_chains():
    from flowslam import geometry as g

    backend = make_backend("odometry", load_config())
    step = g.from_euler("z", 10, t=[1, 0, 0], degrees=True)
    backend.add_odometry(0, None, None)
    for k in range(1, 37):
        backend.add_odometry(k, step, np.eye(6))
    traj = backend.trajectory()
    assert traj.shape == (37, 4, 4)
    np.testing.assert_allclose(traj[0], np.eye(4))
    np.testing.assert_allclose(traj[-1], np.eye(4), atol=1e-9)  # a full circle
    np.testing.assert_allclose(traj[2], step @ step)
