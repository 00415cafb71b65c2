"""Reader of sequences written by the flowslam LiDAR simulator (``flowslam simulate``).

The layout is KITTI odometry's (see ``flowslam.simulation.writer``) plus a
``manifest.json`` at the root, by which ``open_dataset`` recognises it. This reader
is the KITTI reader with the simulator's conventions:

- no elevation correction (``vertical_correction_deg`` = 0): the points are exactly as
  simulated (KITTI's 0.205 deg correction is for the real HDL-64E's calibration error);
- ``calib.txt``'s ``Tr`` is the identity (the LiDAR is the "camera 0" frame), so
  ``gt_poses`` = ``poses/00.txt`` = ``T_world_sensor`` at each frame timestamp, world = the
  first frame's sensor frame;
- per frame, ``gt/<frame>.npz`` gives ``gt_flow`` (Argoverse 2 convention: ``p + flow``
  is the same physical point at the next frame's timestamp plus the point's firing offset,
  in the sensor frame of that instant), ``gt_dynamic`` (world speed > 0.5 m/s),
  ``gt_class`` (ids in ``manifest["classes"]``), ``gt_instance`` (-1 = ground);
  ``extras`` gets ``flow_compensated`` (the object's own motion in the point's sensor
  frame), ``beam`` and ``column``, and the labels the scene-flow metrics read
  (``simulated_to_av2``): ``av2_category`` (car -> REGULAR_VEHICLE, truck -> TRUCK,
  cyclist -> BICYCLIST, pedestrian -> PEDESTRIAN, everything else background) and
  ``is_ground`` (road, sidewalk, terrain);
- ``point_times`` (s after the frame timestamp) only when the sequence was simulated
  with motion distortion; then each point is in the sensor frame at its own firing time,
  as a raw spinning LiDAR reports it (``deskewed(i)`` re-expresses frame i in the sensor
  frame at its timestamp). Without distortion the scan is instantaneous and
  ``point_times`` is None.
"""

from __future__ import annotations

import json
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

from flowslam.frame import Frame
from flowslam.datasets.kitti import KittiOdometry
from flowslam.errors import InputError

_SIM_TO_AV2 = {"car": "REGULAR_VEHICLE", "truck": "TRUCK", "cyclist": "BICYCLIST", "pedestrian": "PEDESTRIAN"}
_SIM_GROUND = ("road", "sidewalk", "terrain")


@lru_cache(maxsize=1)
def _av2_lookup() -> tuple[np.ndarray, np.ndarray]:
    """Simulator class id -> (Argoverse 2 category index, is_ground), built once."""
    from flowslam.sceneflow.metrics import AV2_CATEGORIES
    from flowslam.simulation.labels import CLASS_NAMES

    lut = np.zeros(max(CLASS_NAMES) + 1, dtype=np.int64)
    ground = np.zeros(max(CLASS_NAMES) + 1, dtype=bool)
    for cid, name in CLASS_NAMES.items():
        if name in _SIM_TO_AV2:
            lut[cid] = AV2_CATEGORIES.index(_SIM_TO_AV2[name])
        ground[cid] = name in _SIM_GROUND
    return lut, ground


def simulated_to_av2(classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Argoverse 2 category index per point, is_ground) for simulator class ids."""
    lut, ground = _av2_lookup()
    c = np.asarray(classes, dtype=np.int64)
    return lut[c], ground[c]


MANIFEST = "manifest.json"
FORMAT = "flowslam-simulation"


def find_simulation_root(path: str | Path) -> Path | None:
    """The simulation root (folder with the manifest) for a root, ``sequences/XX`` or
    ``sequences/XX/velodyne`` path; None if ``path`` is not inside a simulated sequence."""
    path = Path(path)
    for cand in (path, path.parent.parent, path.parent.parent.parent):
        m = cand / MANIFEST
        if m.is_file():
            try:
                head = m.read_text()[:4096]
            except OSError:
                return None
            return cand if FORMAT in head else None
    return None


def is_simulated(path: Path) -> bool:
    return path.is_dir() and find_simulation_root(path) is not None


class SimulatedSequence(KittiOdometry):
    """A simulated sequence (module doc). ``path``: the simulation root (or its
    ``sequences/00`` / ``velodyne`` folder); ``fix_times`` as for KITTI."""

    name = "simulated"

    def __init__(self, path: str | Path, sequence: str | int | None = None, fix_times: bool = False):
        path = Path(path)
        if not path.exists():
            raise InputError(path, "does not exist")
        root = find_simulation_root(path)
        if root is None:
            raise InputError(path, f"no {MANIFEST} of a flowslam simulation here (or two levels up)")
        try:
            self.manifest = json.loads((root / MANIFEST).read_text())
        except (OSError, ValueError) as e:
            raise InputError(root / MANIFEST, f"cannot read the manifest ({e})") from None
        super().__init__(path, sequence=sequence, vertical_correction_deg=0.0, fix_times=fix_times)
        self.root = root
        self.gt_dir = self.sequence_dir / "gt"
        self.distortion = bool(self.manifest.get("distortion", False))
        self.class_names = {int(k): v["name"] for k, v in self.manifest.get("classes", {}).items()}

    def describe(self) -> str:
        m = self.manifest
        return (f"simulated ({m.get('preset')}, seed {m.get('seed')}, {m.get('sensor', {}).get('name')}, "
                f"{len(self)} frames) at {self.root}")

    def _load(self, index: int) -> Frame:
        frame = super()._load(index)
        gt_path = self.gt_dir / (self.scan_files[index].stem + ".npz")
        try:
            gt = np.load(gt_path)
            arrays = {k: gt[k] for k in gt.files}
        except FileNotFoundError:
            raise InputError(gt_path, "ground-truth file missing") from None
        except (OSError, ValueError) as e:
            raise InputError(gt_path, f"cannot read ground truth ({e})") from None
        n = len(frame.points)
        for key, arr in arrays.items():
            if len(arr) != n:
                raise InputError(gt_path, f"{key} has {len(arr)} rows but the scan has {n} points")
        frame.gt_flow = arrays["flow"].astype(np.float64)
        frame.gt_dynamic = arrays["dynamic"].astype(bool)
        frame.gt_class = arrays["class"].astype(np.int64)
        frame.gt_instance = arrays["instance"].astype(np.int64)
        frame.point_times = arrays["times"].astype(np.float64) if self.distortion else None
        frame.extras["flow_compensated"] = arrays["flow_compensated"].astype(np.float64)
        frame.extras["beam"] = arrays["beam"].astype(np.int64)
        frame.extras["column"] = arrays["column"].astype(np.int64)
        frame.extras["av2_category"], frame.extras["is_ground"] = simulated_to_av2(frame.gt_class)
        return frame

    @cached_property
    def scene(self):
        """The ego and actor tracks and shapes (``flowslam.simulation.scene_io.SceneRecord``)."""
        from flowslam.simulation.scene_io import load_actors

        return load_actors(self.sequence_dir / "actors.npz")

    def pose_at(self, t) -> np.ndarray:
        """``T_world_sensor`` (world = the first frame's sensor frame) at time(s) ``t`` on the
        frames' time axis, e.g. ``timestamps + sweep_period`` for the sweep ends: exact, the
        simulator's own interpolation. (N,4,4) for an array, (4,4) for a scalar."""
        from flowslam import geometry

        scene = self.scene
        T = geometry.inv(scene.T_town_first) @ scene.T_town_sensor(np.atleast_1d(np.asarray(t, dtype=np.float64)))
        return T[0] if np.ndim(t) == 0 else T

    def deskewed(self, index: int) -> np.ndarray:
        """Points of frame ``index`` in the sensor frame at the frame timestamp (each point's
        world position at its firing time): an exact motion compensation."""
        from flowslam.simulation.ground_truth import deskew

        frame = self[index]
        if frame.point_times is None:
            return frame.points.copy()
        scene = self.scene
        return deskew(frame.points, frame.point_times, scene.ego, float(self.timestamps[index]))
