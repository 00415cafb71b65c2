"""Sensor models: beam elevation tables as specified, and the ray caster's geometry
(elevation, azimuth and firing time of every returned point), measured on a scan."""

from __future__ import annotations

import numpy as np
import pytest

from flowslam.errors import InputError
from flowslam.simulation import labels
from flowslam.simulation.meshes import ellipsoid
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.sensors import (
    SENSORS,
    VLP32C_ELEVATIONS_DEG,
    get_sensor,
)


def test_hdl64_has_kittis_geometry():
    e = np.array(SENSORS["hdl64"].heads[0].elevations_deg)
    assert len(e) == 64 and SENSORS["hdl64"].beams == 64
    assert e.max() == pytest.approx(2.0) and e.min() == pytest.approx(-24.8)
    assert np.all(np.diff(e) < 0)
    # upper block 1/3 deg apart, lower block ~1/2 deg apart
    assert np.allclose(np.diff(e[:32]), -1 / 3, atol=1e-5)
    assert np.allclose(np.diff(e[32:]), np.diff(e[32:]).mean(), atol=1e-5)
    assert -0.53 < np.diff(e[32:]).mean() < -0.49
    assert SENSORS["hdl64"].ground_height == pytest.approx(1.73)


def test_vlp16_vlp32c_os1_tables():
    assert np.array_equal(SENSORS["vlp16"].heads[0].elevations_deg, np.arange(-15.0, 16.0, 2.0))
    v32 = np.array(VLP32C_ELEVATIONS_DEG)
    assert len(v32) == 32 and v32.min() == -25.0 and v32.max() == 15.0
    dense = v32[np.abs(v32) <= 2.0]  # dense around the horizon: 1/3 deg apart
    assert len(dense) == 12 and np.allclose(np.diff(dense), 1 / 3, atol=2e-3)
    os1 = np.array(SENSORS["os1-128"].heads[0].elevations_deg)
    assert len(os1) == 128 and os1.max() == pytest.approx(22.5) and os1.min() == pytest.approx(-22.5)
    assert np.allclose(np.diff(os1), -45.0 / 127, atol=1e-5)


def test_av2_pair_is_two_vlp32c_one_upside_down():
    up, down = SENSORS["av2"].heads
    assert np.array_equal(up.elevations_deg, VLP32C_ELEVATIONS_DEG)
    assert np.array_equal(down.elevations_deg, tuple(-e for e in VLP32C_ELEVATIONS_DEG))
    assert up.spin == 1 and down.spin == -1
    assert up.offset[2] > down.offset[2]
    assert SENSORS["av2"].beams == 64


def test_options_and_bad_values():
    s = get_sensor("vlp16", columns=360, max_range=50.0, range_noise=0.0, dropout=0.1)
    assert (s.columns, s.max_range, s.range_noise, s.dropout) == (360, 50.0, 0.0, 0.1)
    assert SENSORS["vlp16"].columns == 1800  # the registry is not modified
    with pytest.raises(InputError):
        get_sensor("hdl-65")
    with pytest.raises(InputError):
        get_sensor("vlp16", dropout=1.5)
    with pytest.raises(InputError):
        get_sensor("vlp16", columns=3)


class _World:
    """A minimal static world: a closed dome of radius 40 m around the sensor."""

    def __init__(self, height):
        self.mesh = ellipsoid((40.0, 40.0, 40.0), (0.0, 0.0, height), 24, 48, label=1)
        self.instance_class = np.array([0, labels.BUILDING])
        self.class_raster = np.full((1, 1), labels.ROAD, dtype=np.uint8)
        self.origin = np.zeros(2)
        self.resolution = 1.0

    def ground_class(self, xy):
        return np.full(len(xy), labels.ROAD, dtype=np.uint8)


class _NoActors:
    actors: list = []
    shapes: list = []
    times = np.array([0.0, 1.0])


@pytest.mark.parametrize("name", list(SENSORS))
def test_scan_geometry_matches_the_model(name):
    """Every point of a scan lies at its beam's elevation and its column's azimuth, seen
    from its head; with distortion its time is its column's firing time."""
    from flowslam.simulation.ground_truth import make_frame
    from flowslam.simulation.raycast import Raycaster

    sensor = get_sensor(name, columns=180, range_noise=0.0)
    world = _World(sensor.ground_height)
    caster = Raycaster(world, _NoActors(), sensor)
    still = PoseTrack(np.array([0.0, 1.0]), np.zeros(2), np.zeros(2), np.zeros(2))
    raw = caster.cast(0.0, still, distortion=True)
    f = make_frame(raw, caster, still, 0.0, 0.1, True, np.random.default_rng(0))
    assert len(f.points) == sensor.beams * sensor.columns  # the dome closes every ray
    elev, head, offsets, spin, phase = sensor.beam_table()
    rel = f.points.astype(np.float64) - offsets[f.beam]
    measured_el = np.degrees(np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1])))
    assert np.allclose(measured_el, np.degrees(elev[f.beam]), atol=1e-3)
    az = np.arctan2(rel[:, 1], rel[:, 0])
    expected_az = np.pi + phase[f.beam] - spin[f.beam] * 2 * np.pi * f.column / sensor.columns
    assert np.allclose(np.angle(np.exp(1j * (az - expected_az))), 0.0, atol=1e-4)
    assert np.allclose(f.times, f.column * sensor.sweep_period / sensor.columns, atol=1e-7)
    # the first column of an upright head looks straight backwards
    first = (f.column == 0) & (spin[f.beam] > 0) & (phase[f.beam] == 0)
    assert np.all(rel[first, 0] < 0) and np.allclose(rel[first, 1], 0.0, atol=1e-3)
    # returns below the horizon hit the ground (analytic plane): z = -height of the head
    down = f.cls == labels.ROAD
    assert down.any()
    assert np.allclose(f.points[down, 2], -sensor.ground_height, atol=1e-5)
