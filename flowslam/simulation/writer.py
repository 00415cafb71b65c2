"""Writing a simulated sequence in the KITTI odometry layout plus ground-truth files.

::

    OUT/
      manifest.json                 what was simulated (sensor, preset, seed, counts, versions)
      poses/00.txt                  T_world_sensor per frame, KITTI format, world = first frame
      sequences/00/
        velodyne/000000.bin ...     float32 x y z intensity, sensor frame (see ground_truth)
        times.txt                   frame timestamps (s, first = 0)
        calib.txt                   P0..P3 = [I|0] and Tr = identity: the LiDAR *is* the
                                    "camera 0" frame, so poses/00.txt are LiDAR poses as they are
        gt/000000.npz ...           per point, in .bin order: flow, flow_compensated (float32 N x 3),
                                    dynamic (bool), class (uint8), instance (int32), times
                                    (float32 s after the frame timestamp), beam, column (uint16)
        actors.npz                  ego and actor poses over time (town frame), actor shapes
        town.npz                    the static world: mesh, instance table, ground-class raster

The ``.npz`` files are zip archives of ``.npy`` arrays (``numpy.load`` reads them),
deflate-compressed at level 1 (fast), except ``flow`` (stored: float noise compresses
little and slowly). Frames are written by a background thread
so that compression overlaps the ray casting of the next frame.
"""

from __future__ import annotations

import io
import json
import queue
import threading
import zipfile
from pathlib import Path

import numpy as np

SEQUENCE = "00"


STORED = ("flow",)
"""Arrays stored without compression (float noise: deflate gains ~40 % for 10x the time)."""


def save_npz(path: Path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """Like ``numpy.savez_compressed`` but with a fast compression level (or none), and
    the ``STORED`` arrays left uncompressed; reproducible bytes (fixed zip timestamps)."""
    tmp = path.with_name(path.name + ".tmp")
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(tmp, "w", compression=mode, compresslevel=1 if compress else None) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))  # reproducible bytes
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arr), allow_pickle=False)
            this = zipfile.ZIP_STORED if name in STORED else mode
            zf.writestr(info, buf.getvalue(), compress_type=this,
                        compresslevel=1 if this == zipfile.ZIP_DEFLATED else None)
    tmp.replace(path)


def kitti_line(T: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in np.asarray(T)[:3, :4].reshape(-1))


class SequenceWriter:
    def __init__(self, root: Path, compress: bool = True, threaded: bool = True):
        self.root = Path(root)
        self.seq = self.root / "sequences" / SEQUENCE
        self.velo = self.seq / "velodyne"
        self.gt = self.seq / "gt"
        for d in (self.velo, self.gt, self.root / "poses"):
            d.mkdir(parents=True, exist_ok=True)
        self.compress = compress
        self._error: BaseException | None = None
        self._queue: queue.Queue | None = None
        if threaded:
            self._queue = queue.Queue(maxsize=3)
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                self._write(*item)
            except BaseException as e:  # reported by finish()
                self._error = e
                return

    def _write(self, index: int, frame) -> None:
        xyzi = np.column_stack([frame.points, frame.intensity]).astype("<f4")
        xyzi.tofile(self.velo / f"{index:06d}.bin")
        save_npz(self.gt / f"{index:06d}.npz", frame.arrays(), self.compress)

    def write(self, index: int, frame) -> None:
        if self._error is not None:
            raise self._error
        if self._queue is None:
            self._write(index, frame)
        else:
            self._queue.put((index, frame))

    def close(self) -> None:
        if self._queue is not None:
            self._queue.put(None)
            self._thread.join()
            self._queue = None
        if self._error is not None:
            raise self._error

    def finish(self, poses_rel: np.ndarray, times: np.ndarray) -> None:
        self.close()
        (self.root / "poses" / f"{SEQUENCE}.txt").write_text("".join(kitti_line(T) + "\n" for T in poses_rel))
        (self.seq / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
        eye = kitti_line(np.eye(4))
        (self.seq / "calib.txt").write_text("".join(f"{k}: {eye}\n" for k in ("P0", "P1", "P2", "P3", "Tr")))


def write_json(path: Path, data: dict) -> None:
    Path(path).write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")
