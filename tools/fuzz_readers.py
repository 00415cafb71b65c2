"""Fuzz the readers for longer than CI does: the generators and the property of
``tests/test_fuzz_readers.py`` (``tests/fuzz_inputs.py``), with fresh random seeds.

    .venv/bin/python tools/fuzz_readers.py --minutes 5
    .venv/bin/python tools/fuzz_readers.py --examples 2000 --readers pcd,ply

Every generated input must give a valid result whose size agrees with the header and
the data, or an ``InputError`` of one line. Prints the inputs tried per reader, the
outcomes, and every failure (Hypothesis' shrunk example); exits 1 if there was one.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import fuzz_inputs  # noqa: E402  (tests/ is not a package; the generators live there)

BATCH = 300
"""Inputs per Hypothesis run in ``--minutes`` mode (each run gets a new seed)."""


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    size = p.add_mutually_exclusive_group()
    size.add_argument("--examples", type=int, help="inputs per reader (one run each)")
    size.add_argument("--minutes", type=float, help="run batches of inputs over all readers for this long")
    p.add_argument("--readers", default=",".join(fuzz_inputs.READERS),
                   help=f"comma-separated subset of {', '.join(fuzz_inputs.READERS)}")
    p.add_argument("--seed", type=int, default=int(time.time()), help="first seed (default: the time)")
    args = p.parse_args()
    if args.examples is None and args.minutes is None:
        args.minutes = 5.0
    unknown = set(args.readers.split(",")) - set(fuzz_inputs.READERS)
    if unknown:
        p.error(f"unknown reader(s) {sorted(unknown)}")
    return args


def _one_run(reader: str, folder: Path, examples: int, seed: int, failures: list[str]) -> None:
    try:
        fuzz_inputs.fuzz(reader, folder, examples, derandomize=False, run_seed=seed)
    except Exception as e:  # noqa: BLE001 - report every failure, keep fuzzing the others
        text = "".join(traceback.format_exception_only(type(e), e)).strip()
        failures.append(f"{reader} (seed {seed}): {text}")
        print(f"FAILURE {failures[-1]}", flush=True)


def main() -> int:
    args = _parse()
    logging.disable(logging.WARNING)  # the readers' expected warnings (NaN points dropped, a wrong POINTS)
    warnings.simplefilter("ignore")  # numpy on corrupt data (signalling NaNs, a Python 2 .npy header)
    readers = args.readers.split(",")
    failures: list[str] = []
    start = time.monotonic()
    seed = args.seed
    with tempfile.TemporaryDirectory(prefix="fuzz_readers_") as tmp:
        folder = Path(tmp)
        if args.examples is not None:
            for reader in readers:
                _one_run(reader, folder, args.examples, seed, failures)
        else:
            deadline = start + 60 * args.minutes
            while time.monotonic() < deadline:
                for reader in readers:
                    if time.monotonic() >= deadline:
                        break
                    _one_run(reader, folder, BATCH, seed, failures)
                    seed += 1
    minutes = (time.monotonic() - start) / 60
    print(f"\nfuzzed for {minutes:.1f} min, first seed {args.seed}")
    for reader in readers:
        outcomes = {k[1]: v for k, v in fuzz_inputs.OUTCOMES.items() if k[0] == reader}
        print(f"  {reader:18s} {fuzz_inputs.TRIED[reader]:7d} inputs  {outcomes}")
    print(f"  {'total':18s} {sum(fuzz_inputs.TRIED.values()):7d} inputs, {len(failures)} failure(s)")
    for f in failures:
        print(f"  FAILURE {f}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
