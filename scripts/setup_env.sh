#!/usr/bin/env bash
# Create (or reuse) .venv with everything der_ros needs, pinned by constraints.txt.
# Idempotent: a second run only checks a stamp and returns.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv
# Foxglove's JavaScript libraries for test/test_interop_foxglove.py, pinned by test/js/package-lock.json
# (node 20 + npm; the test runs `npm ci` itself if this could not)
if command -v npm >/dev/null 2>&1 && [ ! -d test/js/node_modules/@mcap/core ]; then
  echo "[setup] npm ci in test/js (Foxglove interop test)" >&2
  (cd test/js && npm ci --no-audit --no-fund --loglevel=error >/dev/null) \
    || echo "[setup] npm ci in test/js failed; test/test_interop_foxglove.py will try again" >&2
fi
stamp_src=$(cat requirements.txt requirements-dev.txt constraints.txt setup.py package.xml | sha256sum | cut -d' ' -f1)
if [ -x "$VENV/bin/python" ] && [ "$(cat "$VENV/.der_stamp" 2>/dev/null)" = "$stamp_src" ]; then
  exit 0
fi
echo "[setup] creating/updating $VENV (first run takes a few minutes)" >&2
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet -c constraints.txt -r requirements.txt -r requirements-dev.txt
# setuptools warns about editable installs on stderr; keep that out of the way unless it fails
if ! "$VENV/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e . > "$VENV/.der_editable.log" 2>&1; then
  cat "$VENV/.der_editable.log" >&2
  exit 1
fi
"$VENV/bin/python" -c "import rclpy, libsumo, torch, der_ros" >/dev/null
echo "$stamp_src" > "$VENV/.der_stamp"
echo "[setup] done" >&2
