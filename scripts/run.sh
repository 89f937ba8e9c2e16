#!/usr/bin/env bash
# README command 1: set everything up, then run the main job: the ROS 2 graph (SUMO bridge, DER agent, MCAP recorder) training on the ring.
# Extra arguments go to the job (see `der graph --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/der graph --scenario ring --steps 15000 "$@"
