#!/usr/bin/env bash
# The shielded ring agents of `der table3 --shield rss` evaluated again (docs/safety.md, "What was measured"):
#   on1000  shield on, 1,000 report episodes per run
#   off300  the same agents with the shield off, 300
#   dense_on / careless_on    shield on under the two shifted settings of config/shift/, 200
#   dense_off / careless_off  the same with the shield off, 200
# Usage, from the repository root: research/shield/evals.sh [TABLE3_RING_DIR] [OUT]   (METHODS="dqn der0.5 ...")
# Then: python research/shield/eval_table.py OUT. A finished <setting>/<method>.json is not redone.
set -euo pipefail
T=${1:-runs/table3/ring}
O=${2:-runs/shield_eval}
for m in ${METHODS:-dqn der0.1 der0.5 der0.9 per}; do
  runs=$(ls -d "$T/$m+shield"/seed*)
  ev() {
    name=$1; shift
    [ -f "$O/$name/$m.json" ] && return
    mkdir -p "$O"
    .venv/bin/der evaluate $runs --seed-set report --json "$O/$name/$m.json" --out "$O/$name/runs" "$@" > "$O/$name.$m.log" 2>&1
  }
  ev on1000 --episodes 1000
  ev off300 --episodes 300 --safety none
  ev dense_on --episodes 200 --traffic config/shift/ring_dense.yaml
  ev careless_on --episodes 200 --traffic config/shift/ring_careless.yaml
  ev dense_off --episodes 200 --traffic config/shift/ring_dense.yaml --safety none
  ev careless_off --episodes 200 --traffic config/shift/ring_careless.yaml --safety none
done
