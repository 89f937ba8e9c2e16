#!/usr/bin/env bash
# README command 2: set everything up, then run the test suite.
# Extra arguments go to pytest (e.g. `-m "not slow"`, `-k replay`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/python -m pytest test "$@"
