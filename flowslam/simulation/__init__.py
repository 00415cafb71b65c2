"""LiDAR simulator: procedural towns, moving actors, ray-cast sensors, exact ground truth.

Library entry points (imported lazily, so ``import flowslam.simulation`` is cheap):

- ``simulate(out_dir, preset="dt", frames=None, seed=0, sensor=None, ...) -> manifest``
  writes a sequence in the KITTI odometry layout with per-frame ground truth
  (``simulator.py``, ``writer.py``);
- ``write_preview(out_dir) -> Path``: a PNG top view of a simulated sequence;
- ``ensure_demo_sequence(cache_dir=None) -> Path``: the embedded default sequence;
  ``ensure_sequence(name, settings, cache_dir=None) -> Path``: any simulated sequence,
  cached the same way (the benchmark suite);
- ``PRESETS`` / ``preset_names()`` and ``SENSORS`` / ``sensor_names()``.

Modules, one job each: ``sensors`` (LiDAR models), ``meshes`` (primitives, actor
shapes), ``paths`` (polylines, pose tracks), ``roads`` (road networks, lanes,
crosswalks), ``town`` (the static world), ``ego_path`` (the ego's route and motion),
``traffic`` (``simulate_traffic``: runs the traffic stages below), ``traffic_spec``
(``TrafficSpec``, ``DT``), ``traffic_scripted`` (convoy, oncoming stream, the ego
group), ``traffic_spawn`` (placing actors), ``traffic_stepping`` (IDM kinematics, right
of way), ``traffic_validation`` (footprint overlap checks), ``actors`` (``Actor``,
``ActorSet``), ``selection`` (actors for a target amount of dynamic points),
``raycast`` (Open3D ray casting), ``ground_truth`` (points, flow, labels),
``presets``, ``writer``, ``scene_io`` (actors.npz, town.npz), ``preview``, ``demo``.
The reader is ``flowslam.datasets.simulated``.
"""

from __future__ import annotations

__all__ = [
    "simulate", "write_preview", "ensure_demo_sequence", "ensure_sequence", "PRESETS", "preset_names", "SENSORS", "sensor_names",
]

_LAZY = {
    "simulate": ("flowslam.simulation.simulator", "simulate"),
    "write_preview": ("flowslam.simulation.preview", "write_preview"),
    "ensure_demo_sequence": ("flowslam.simulation.demo", "ensure_demo_sequence"),
    "ensure_sequence": ("flowslam.simulation.demo", "ensure_sequence"),
    "PRESETS": ("flowslam.simulation.presets", "PRESETS"),
    "preset_names": ("flowslam.simulation.presets", "preset_names"),
    "SENSORS": ("flowslam.simulation.sensors", "SENSORS"),
    "sensor_names": ("flowslam.simulation.sensors", "sensor_names"),
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'flowslam.simulation' has no attribute {name!r}")
