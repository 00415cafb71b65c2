#!/usr/bin/env bash
# Create the virtual environment and install flowslam into it (used by the Makefile).
#   VENV        where to create it (default .venv)
#   PYTHON      interpreter to build it from (default python3; needs >= 3.11)
#   TORCH_SPEC  the torch requirement (default torch==2.13.0, the CPU build here);
#               e.g. TORCH_SPEC="torch==2.13.0" TORCH_PIP_ARGS="--index-url <your CUDA index>"
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
TORCH_PIP_ARGS=${TORCH_PIP_ARGS:-}

# Open3D links against libusb-1.0 (Debian: libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1\.0\.so\.0'; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing libusb-1.0-0 (needed by Open3D)"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "setup: Open3D needs libusb-1.0. Install it first, then re-run:" >&2
        echo "    sudo apt-get install -y libusb-1.0-0" >&2
        exit 1
    fi
fi

"$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' || {
    echo "setup: flowslam needs Python >= 3.11 ($PYTHON is $("$PYTHON" --version 2>&1))" >&2; exit 1; }

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
# torch first, pinned, so that the package's own `torch` requirement is already met
# and pip never pulls the multi-GB CUDA build by accident.
# shellcheck disable=SC2086
"$VENV/bin/python" -m pip install -q $TORCH_PIP_ARGS "$TORCH_SPEC"
# viz (rerun-sdk) too, so that the 3-D view's tests run here; flowslam itself never needs it.
"$VENV/bin/python" -m pip install -q -e ".[dev,viz]"
echo "setup: flowslam installed in $VENV"
# numba's kernels compiled once here (~30 s on 2 cores) instead of in the first run; a
# failure only leaves that first run slower (flowslam/warmup.py)
echo "setup: compiling flowslam's kernels"
"$VENV/bin/python" -m flowslam.warmup || true
