"""Semantic classes of the simulated world: ids, names, preview colours, reflectivity.

The ids are flowslam's own (written to ``manifest.json`` under ``classes``).
``UNLABELED`` is never emitted for a point (every returned ray hit something).
Instance ids: ``-1`` for "stuff" (ground: road, sidewalk, terrain); static things
(buildings, walls, fences, trees, poles, parked cars) have ids ``1..``; moving
actors have ids from ``ACTOR_ID_BASE`` on.
"""

from __future__ import annotations

import numpy as np

UNLABELED = 0
ROAD = 1
SIDEWALK = 2
TERRAIN = 3
BUILDING = 4
WALL = 5
FENCE = 6
VEGETATION = 7
POLE = 8
CAR = 9
TRUCK = 10
CYCLIST = 11
PEDESTRIAN = 12

CLASS_NAMES = {
    UNLABELED: "unlabeled",
    ROAD: "road",
    SIDEWALK: "sidewalk",
    TERRAIN: "terrain",
    BUILDING: "building",
    WALL: "wall",
    FENCE: "fence",
    VEGETATION: "vegetation",
    POLE: "pole",
    CAR: "car",
    TRUCK: "truck",
    CYCLIST: "cyclist",
    PEDESTRIAN: "pedestrian",
}
NUM_CLASSES = len(CLASS_NAMES)

CLASS_COLORS = np.array(
    [
        [0.0, 0.0, 0.0],  # unlabeled
        [0.45, 0.45, 0.50],  # road
        [0.75, 0.65, 0.75],  # sidewalk
        [0.60, 0.75, 0.45],  # terrain
        [0.85, 0.55, 0.35],  # building
        [0.70, 0.45, 0.35],  # wall
        [0.80, 0.75, 0.40],  # fence
        [0.20, 0.55, 0.20],  # vegetation
        [0.95, 0.85, 0.10],  # pole
        [0.15, 0.35, 0.90],  # car
        [0.10, 0.15, 0.55],  # truck
        [0.90, 0.20, 0.80],  # cyclist
        [0.90, 0.15, 0.15],  # pedestrian
    ]
)
"""RGB in 0..1 per class id (preview)."""

REFLECTIVITY = np.array([0.0, 0.12, 0.22, 0.30, 0.35, 0.40, 0.45, 0.28, 0.60, 0.55, 0.50, 0.45, 0.30])
"""Nominal reflectivity per class id (the simulated intensity's scale)."""

ACTOR_ID_BASE = 100_000
"""Moving actors get instance ids ``ACTOR_ID_BASE + k``; static things are below."""


def class_table() -> dict[str, dict]:
    """``{id: {"name", "color"}}`` as written to the manifest (ids as strings for JSON)."""
    return {
        str(i): {"name": CLASS_NAMES[i], "color": [round(float(c), 3) for c in CLASS_COLORS[i]]}
        for i in CLASS_NAMES
    }
