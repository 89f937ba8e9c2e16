#!/usr/bin/env bash
# README command 2: set everything up, then run the test suite.
# Extra arguments go to pytest: the fast tier (no ROS processes, no Ray, no training/suite smoke
# runs) is `./scripts/test.sh -m "not ros and not slow"`; one layer: `./scripts/test.sh test/replay`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/python -m pytest test "$@"
