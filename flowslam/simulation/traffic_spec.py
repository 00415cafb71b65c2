"""What traffic to simulate: ``TrafficSpec`` (densities near the ego route, the ego's
convoy, the oncoming stream, the dynamic-points target) and ``DT``, the time step of the
traffic simulation.

Units: densities per km of usable track, distances in metres, times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

DT = 0.1
"""Traffic simulation step (s); actor poses are interpolated linearly in between."""


@dataclass
class TrafficSpec:
    """How much traffic (per km of usable track near the ego route)."""

    vehicles_per_km: float = 0.0
    truck_share: float = 0.1
    cyclists_per_km: float = 0.0
    walkers_per_km: float = 0.0
    crossers: float = 0.0
    """Fraction of crosswalks with a crossing pedestrian."""
    convoy: tuple[float, ...] = ()
    """Arc offsets (m, centre to centre) of convoy vehicles on the ego route: + ahead, - behind."""
    oncoming: int = 0
    """Procedural loops: a scripted stream of this many vehicles driving the ego's loops the
    other way (in the oncoming lanes), ``oncoming_headway`` seconds apart."""
    oncoming_headway: float = 2.5
    spawn_radius: float = 160.0
    """Only tracks within this distance of the ego route get vehicles and crossers."""
    walker_radius: float = 60.0
    """Only sidewalk stretches within this distance of the ego route get walkers."""
    target_dynamic: float | None = None
    """Keep only the actors that bring the dynamic points per frame (reference sensor:
    64 x 2048 HDL-64E) closest to this (``selection``); None keeps them all."""
