#!/usr/bin/env bash
# Run bench/replay.py with TorchRL's prioritized buffers too.
#
# TorchRL 0.14.1's compiled extension (its sum trees) is built against torch 2.14, so it does not
# load beside the torch 2.13.0 the project pins. der_ros's replay core does not use torch at all,
# so this script makes a separate benchmark venv (.venv-torchrl, git-ignored; torch 2.14.1 is a
# several-GB CUDA build) holding ours, cpprb and TorchRL, and runs the same script in it: ours
# and both peers still run side by side in one process on the same data.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv-torchrl
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c "import torchrl._torchrl, cpprb, numba, der_ros.replay" 2>/dev/null; then
  echo "[bench] creating $VENV (torch 2.14.1 + torchrl 0.14.1; a few minutes, several GB)" >&2
  python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet torch==2.14.1 torchrl==0.14.1 cpprb numba numpy pyyaml psutil scipy
  "$VENV/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e . > "$VENV/.editable.log" 2>&1
fi
exec "$VENV/bin/python" bench/replay.py "$@"
