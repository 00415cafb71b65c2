"""Spinning LiDAR models: beam elevations, azimuth sampling, timing, range limits, noise.

Sensor frame (the frame of the written points and of ``T_world_sensor``): x forward,
y left, z up, origin ``ground_height`` metres above the (flat) ground, at the
vehicle's centre in x/y unless ``vehicle_center_x`` says otherwise.

A model has one or more *heads* (a physical spinning unit). Each head has its own
origin in the sensor frame and its beam elevations *as seen in the sensor frame*
(an upside-down unit has the device table negated and spins the other way). One
sweep takes ``sweep_period`` seconds and has ``columns`` firing instants per head;
column ``c`` fires at ``tau_c = c / columns * sweep_period`` after the sweep start,
all beams of all heads at once, looking at azimuth::

    az(h, c) = pi + phase_h - spin_h * 2 pi c / columns     (radians, atan2(y, x))

so an upright Velodyne (``spin=+1``, clockwise seen from above) starts looking
backwards and passes the front half-way through the sweep, as KITTI's scans do.

Models (``SENSORS``; ``get_sensor(name, columns=..., ...)`` returns a copy with
options changed):

- ``hdl64``: Velodyne HDL-64E with KITTI's geometry: 64 beams from +2.0 deg down to
  -24.8 deg (upper block of 32 beams from +2.0 to -8.33 deg at 1/3 deg, lower block
  of 32 from -8.83 to -24.8 deg at ~1/2 deg), mounted 1.73 m above the ground,
  2048 columns, 120 m range.
- ``av2``: the Argoverse 2 pair of Velodyne VLP-32C (factory elevation table,
  -25..+15 deg, dense around the horizon): the upper unit upright at (1.35, 0, 1.64) m,
  the lower one upside down at (1.35, 0, 1.525) m (elevations -15..+25 deg, spinning
  the other way), as in AV2's calibration; the sensor frame is AV2's egovehicle
  frame (rear axle), taken 0.33 m above the ground. 1800 columns, 200 m range.
- ``vlp32c``: one upright VLP-32C, 1.8 m above the ground.
- ``vlp16``: Velodyne VLP-16: 16 beams, -15..+15 deg every 2 deg, 1.8 m, 1800 columns, 100 m.
- ``os1-128``: Ouster OS1-128 (rev 6): 128 beams uniformly over +22.5..-22.5 deg,
  1.8 m, 1024 columns, 120 m.

Noise: the range of each return gets Gaussian noise of ``range_noise`` metres (1 sigma)
along its ray; ``dropout`` is the probability that a ray returns nothing.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from flowslam.errors import InputError

VLP32C_ELEVATIONS_DEG = (
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333,
    -3.0, -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667,
    1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0,
)
"""Velodyne VLP-32C factory elevation table (deg), sorted ascending."""

HDL64_ELEVATIONS_DEG = tuple(
    np.concatenate([np.linspace(2.0, -8.0 - 1.0 / 3.0, 32), np.linspace(-8.0 - 5.0 / 6.0, -24.8, 32)]).round(6)
)
"""KITTI's HDL-64E: +2.0 deg .. -24.8 deg, upper block 1/3 deg apart, lower block ~1/2 deg."""

VLP16_ELEVATIONS_DEG = tuple(float(e) for e in np.arange(-15.0, 15.01, 2.0))
OS1_128_ELEVATIONS_DEG = tuple(np.linspace(22.5, -22.5, 128).round(6))


@dataclass(frozen=True)
class LidarHead:
    """One spinning unit: beam elevations (deg, in the sensor frame), origin, spin, phase."""

    elevations_deg: tuple[float, ...]
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Head origin in the sensor frame (m)."""
    spin: int = 1
    """+1: clockwise seen from above (azimuth decreases with time); -1: counter-clockwise."""
    phase_deg: float = 0.0
    """Azimuth offset of the first column relative to straight backwards (deg)."""
    name: str = "lidar"


@dataclass(frozen=True)
class SensorModel:
    """A spinning LiDAR (see the module doc). Immutable; change options with ``with_options``."""

    name: str
    heads: tuple[LidarHead, ...]
    columns: int = 2048
    max_range: float = 120.0
    min_range: float = 1.0
    range_noise: float = 0.02
    dropout: float = 0.0
    sweep_period: float = 0.1
    ground_height: float = 1.73
    """Height of the sensor-frame origin above the ground (m)."""
    vehicle_center_x: float = 0.0
    """x of the ego vehicle's footprint centre in the sensor frame (m)."""
    vehicle_size: tuple[float, float] = (4.6, 1.9)
    """Ego vehicle footprint length and width (m), for collision avoidance."""
    description: str = field(default="", compare=False)

    @property
    def beams(self) -> int:
        return sum(len(h.elevations_deg) for h in self.heads)

    @property
    def rays_per_sweep(self) -> int:
        return self.beams * self.columns

    def with_options(self, **changes) -> "SensorModel":
        """A copy with ``columns``, ``max_range``, ``min_range``, ``range_noise``,
        ``dropout`` or ``sweep_period`` changed (None values are ignored); validated."""
        changes = {k: v for k, v in changes.items() if v is not None}
        model = replace(self, **changes)
        model.validate()
        return model

    def validate(self) -> None:
        if not 16 <= self.columns <= 16384:
            raise InputError(None, f"sensor columns must be in 16..16384, got {self.columns}")
        if not 0 < self.min_range < self.max_range:
            raise InputError(None, f"sensor range must satisfy 0 < min_range < max_range, got {self.min_range}, {self.max_range}")
        if not 0 <= self.range_noise <= 1.0:
            raise InputError(None, f"range noise must be in 0..1 m, got {self.range_noise}")
        if not 0 <= self.dropout < 1.0:
            raise InputError(None, f"dropout must be in [0, 1), got {self.dropout}")
        if not 0 < self.sweep_period <= 1.0:
            raise InputError(None, f"sweep period must be in (0, 1] s, got {self.sweep_period}")

    # ----------------------------------------------------------------- ray tables
    def column_times(self) -> np.ndarray:
        """(C,) firing time of each column after the sweep start (s)."""
        return np.arange(self.columns) * (self.sweep_period / self.columns)

    def beam_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per beam (over all heads, B = ``beams``): elevation (rad), head index, offset (B,3),
        spin (B,), phase (rad, B)."""
        elev, head, off, spin, phase = [], [], [], [], []
        for h, unit in enumerate(self.heads):
            n = len(unit.elevations_deg)
            elev.append(np.deg2rad(np.asarray(unit.elevations_deg, dtype=np.float64)))
            head.append(np.full(n, h))
            off.append(np.tile(np.asarray(unit.offset, dtype=np.float64), (n, 1)))
            spin.append(np.full(n, float(unit.spin)))
            phase.append(np.full(n, np.deg2rad(unit.phase_deg)))
        return (np.concatenate(elev), np.concatenate(head), np.concatenate(off), np.concatenate(spin),
                np.concatenate(phase))

    def azimuths(self) -> np.ndarray:
        """(C, B) azimuth (rad, in (-pi, pi]) of every ray in the sensor frame."""
        _, _, _, spin, phase = self.beam_table()
        c = np.arange(self.columns)[:, None]
        az = np.pi + phase[None, :] - spin[None, :] * (2.0 * np.pi * c / self.columns)
        return np.angle(np.exp(1j * az))

    def ray_directions(self) -> np.ndarray:
        """(C, B, 3) unit ray directions in the sensor frame, column-major (firing order)."""
        elev = self.beam_table()[0]
        az = self.azimuths()
        ce = np.cos(elev)[None, :]
        return np.stack([ce * np.cos(az), ce * np.sin(az), np.broadcast_to(np.sin(elev), az.shape)], axis=-1)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["beams"] = self.beams
        d["heads"] = [
            {**asdict(h), "elevations_deg": [float(e) for e in h.elevations_deg]} for h in self.heads
        ]
        return d


SENSORS: dict[str, SensorModel] = {
    "hdl64": SensorModel(
        "hdl64", (LidarHead(HDL64_ELEVATIONS_DEG, name="hdl64"),), columns=2048, max_range=120.0,
        range_noise=0.02, ground_height=1.73, vehicle_center_x=0.3,
        description="Velodyne HDL-64E, KITTI geometry (+2.0..-24.8 deg)",
    ),
    "av2": SensorModel(
        "av2",
        (
            LidarHead(VLP32C_ELEVATIONS_DEG, offset=(1.35, 0.0, 1.64), spin=1, name="up_lidar"),
            LidarHead(tuple(-e for e in VLP32C_ELEVATIONS_DEG), offset=(1.35, 0.0, 1.525), spin=-1,
                      phase_deg=-11.56, name="down_lidar"),
        ),
        columns=1800, max_range=200.0, range_noise=0.03, ground_height=0.33, vehicle_center_x=1.4,
        description="Argoverse 2: two VLP-32C, the lower one upside down; egovehicle frame",
    ),
    "vlp32c": SensorModel(
        "vlp32c", (LidarHead(VLP32C_ELEVATIONS_DEG, name="vlp32c"),), columns=1800, max_range=200.0,
        range_noise=0.03, ground_height=1.8, description="Velodyne VLP-32C",
    ),
    "vlp16": SensorModel(
        "vlp16", (LidarHead(VLP16_ELEVATIONS_DEG, name="vlp16"),), columns=1800, max_range=100.0,
        range_noise=0.03, ground_height=1.8, description="Velodyne VLP-16 (-15..+15 deg)",
    ),
    "os1-128": SensorModel(
        "os1-128", (LidarHead(OS1_128_ELEVATIONS_DEG, name="os1-128"),), columns=1024, max_range=120.0,
        range_noise=0.015, ground_height=1.8, description="Ouster OS1-128 rev 6 (+22.5..-22.5 deg)",
    ),
}


def sensor_names() -> list[str]:
    return list(SENSORS)


def get_sensor(name: str | SensorModel, **options) -> SensorModel:
    """The model named ``name`` (or a given model) with ``options`` applied (see ``with_options``)."""
    if isinstance(name, SensorModel):
        return name.with_options(**options)
    if name not in SENSORS:
        raise InputError(None, f"unknown sensor {name!r} (available: {', '.join(SENSORS)})")
    return SENSORS[name].with_options(**options)
