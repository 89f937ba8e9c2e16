#!/usr/bin/env bash
# README command 1: set everything up, then run the main job.
# Extra arguments go to the job (see `der graph --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/der train --config config/cartpole.yaml --replay der --lam 0.9 "$@"
