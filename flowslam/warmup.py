"""Compile flowslam's numba kernels once, at set-up, instead of in the user's first run.

``python -m flowslam.warmup`` (the last step of ``tools/setup_env.sh``) simulates a short
sequence in a temporary folder (5 scans of the embedded simulator's ``dt`` town, VLP-16)
and runs the default ``ssf`` + ``isam2`` pipeline on it, with the static map and the
moving-objects log, then the KITTI reader's elevation correction: every compiled kernel
of a run is compiled for the types a run gives it and written to numba's cache
(``__pycache__`` beside the sources, or numba's user cache where that is read-only),
which later processes load in milliseconds.
Measured on the 2-core VM: ``flowslam run -f ssf -b isam2`` on the 16 KITTI scans took
32.8 s with an empty cache and 9.0 s after this warm-up (8.4 s with every kernel cached).

It reads no data from outside the package and writes nothing but numba's cache and a
temporary folder it removes. A failure leaves only a slower first run: the module prints
one line and exits with 1, and set-up goes on.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

WARMUP_FRAMES = 5
WARMUP_SENSOR = "vlp16"


def warm_up() -> float:
    """Simulate and run the short sequence (module doc); the seconds it took."""
    from flowslam.threads import set_thread_defaults

    set_thread_defaults()
    from flowslam.config import PipelineConfig
    from flowslam.datasets import open_dataset
    from flowslam.pipeline import drive
    from flowslam.simulation import simulate
    from flowslam.slam import Slam

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="flowslam-warmup-") as tmp:
        sequence = Path(tmp) / "sequence"
        simulate(sequence, preset="dt", frames=WARMUP_FRAMES, seed=7, sensor=WARMUP_SENSOR, workers=1)
        config = PipelineConfig.model_validate({"frontend": "ssf", "backend": "isam2"})
        result = drive(Slam(config), open_dataset(sequence, config.dataset))
        if result.error is not None:
            raise result.error
    import numpy as np

    from flowslam.datasets.kitti import correct_elevation

    correct_elevation(np.zeros((1, 3)), 0.0)  # the KITTI reader's kernel (the simulated scans do not use it)
    return time.perf_counter() - start


def main() -> int:
    try:
        seconds = warm_up()
    except Exception as error:  # noqa: BLE001 -- set-up goes on: the first run compiles instead
        print(f"flowslam warm-up: not done ({type(error).__name__}: {error}); the first run compiles the kernels",
              file=sys.stderr)
        return 1
    print(f"flowslam warm-up: kernels compiled and cached in {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
