"""Named scenarios: town, route, traffic and sensor defaults (deterministic from the seed).

=============  =====================================================================
``static``     the town with parked cars, nothing moves (0 dynamic points)
``dh``         D^H-like: few movers, ~100 dynamic points per frame on average
``dt``         D^T-like: regular traffic and a lead car, ~4,000 dynamic points per frame
``rush-hour``  dense traffic, crowded sidewalks, a lead and a following car, a stream of
               oncoming cars: >= 20 % of the points dynamic
``kitti00-path`` the real KITTI-00 ground-truth path (3.7 km, real loops) with a town
               grown around it, traffic in the oncoming lane and a lead car: ~1,500 dynamic
               points per frame
``demo``       the embedded default (``flowslam demo``): a small town, a block loop
               closed within 250 frames of a 64 x 1024 sensor, dt-like traffic
=============  =====================================================================

Every preset can be combined with any sensor and with motion distortion on or off.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from flowslam.errors import InputError
from flowslam.simulation.town import TownStyle
from flowslam.simulation.traffic_spec import TrafficSpec


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    traffic: TrafficSpec
    frames: int = 300
    sensor: str = "hdl64"
    columns: int | None = None
    route: str = "loop"
    """"loop" (block loops in a procedural town) or "trajectory" (a given path)."""
    cruise: float = 10.0
    grid: tuple[int, int] = (5, 5)
    block: tuple[float, float] = (40.0, 62.0)
    town: TownStyle = field(default_factory=TownStyle)
    dynamic_target: str = ""
    """The intended amount of dynamic points, in words (documentation and manifest)."""
    trajectory: str | None = None
    """Default trajectory file (name under the shared data's ``trajectories/``)."""


PRESETS: dict[str, Preset] = {
    "static": Preset(
        "static", "a town with parked cars and nothing moving", TrafficSpec(),
        dynamic_target="0 dynamic points",
    ),
    "dh": Preset(
        "dh", "few movers (SSF-PAN's D^H: ~100 dynamic points per frame)",
        TrafficSpec(vehicles_per_km=3.0, truck_share=0.05, cyclists_per_km=1.0, walkers_per_km=12.0,
                    crossers=0.3, target_dynamic=100.0),
        dynamic_target="~100 dynamic points per frame (64 x 2048 sensor)",
    ),
    "dt": Preset(
        "dt", "regular traffic with a lead car (SSF-PAN's D^T: ~4,000 dynamic points per frame)",
        TrafficSpec(vehicles_per_km=24.0, cyclists_per_km=4.0, walkers_per_km=80.0, crossers=0.8, convoy=(17.0,),
                    target_dynamic=4000.0),
        dynamic_target="~4,000 dynamic points per frame (64 x 2048 sensor)",
    ),
    "rush-hour": Preset(
        "rush-hour", "dense traffic, crowded sidewalks, a lead and a following car, oncoming stream",
        TrafficSpec(vehicles_per_km=40.0, truck_share=0.12, cyclists_per_km=6.0, walkers_per_km=500.0,
                    crossers=1.0, convoy=(12.5, -11.5), oncoming=20, oncoming_headway=2.0),
        town=TownStyle(parked_fill=0.05, tree_prob=0.4),
        dynamic_target=">= 20 % of the points dynamic",
    ),
    "kitti00-path": Preset(
        "kitti00-path", "the real KITTI-00 path with a town around it, oncoming traffic, a lead car",
        TrafficSpec(vehicles_per_km=30.0, cyclists_per_km=5.0, walkers_per_km=60.0, crossers=0.8, convoy=(20.0,),
                    target_dynamic=1500.0),
        route="trajectory", trajectory="kitti00_gt_poses.txt",
        town=TownStyle(building_prob=0.95, building_gap=(0.5, 4.0)),
        dynamic_target="~1,500 dynamic points per frame (64 x 2048 sensor)",
    ),
    "demo": Preset(
        "demo", "the embedded default: one block loop closed within the sequence, dt-like traffic",
        TrafficSpec(vehicles_per_km=24.0, cyclists_per_km=4.0, walkers_per_km=80.0, crossers=0.8, convoy=(17.0,),
                    target_dynamic=4000.0),
        frames=250, columns=1024, cruise=10.0, grid=(4, 4), block=(34.0, 46.0),
        town=TownStyle(building_depth=(5.0, 9.0), building_width=(6.0, 16.0), building_gap=(0.5, 4.0)),
        dynamic_target="~4,000 dynamic points per frame on a 64 x 2048 sensor (~2,000 on the demo's 64 x 1024)",
    ),
}


def preset_names() -> list[str]:
    return list(PRESETS)


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise InputError(None, f"unknown preset {name!r} (available: {', '.join(PRESETS)})")
    return PRESETS[name]
