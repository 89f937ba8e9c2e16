#!/usr/bin/env bash
# Run benchmark scripts from an older commit and from this tree, alternating new, old, old, new.
#
#   bash bench/old_vs_new.sh OLD_COMMIT OUT_DIR SCRIPT[:ARGS] ...
#   bash bench/old_vs_new.sh 9bda61a /tmp/oldnew replay train replay_io "sumo_env:--no-policies" render bag_writer
#
# The old commit is checked out (detached) in a temporary git worktree and runs its own copy of each
# script with PYTHONPATH pointing at it; both use this tree's .venv. Each run's output goes to
# OUT_DIR/<script>_<new|old>.<n>.txt (its last line is the script's JSON). Run it on an idle machine:
# the ratios are only as good as the alternation.
set -euo pipefail
[ $# -ge 3 ] || { sed -n 2,9p "$0"; exit 2; }
old_commit=$1 out=$2; shift 2
here=$(cd "$(dirname "$0")/.." && pwd)
git -C "$here" rev-parse --verify -q "$old_commit^{commit}" > /dev/null || { echo "not a commit: $old_commit" >&2; exit 2; }
mkdir -p "$out"
old=$(mktemp -d /tmp/der_old_tree.XXXXXX)
trap 'git -C "$here" worktree remove --force "$old" 2> /dev/null || rm -rf "$old"' EXIT
git -C "$here" worktree add --detach -q "$old" "$old_commit"
ln -s "$here/.venv" "$old/.venv"
for spec in "$@"; do
  script=${spec%%:*} args=""
  [ "$spec" != "$script" ] && args=${spec#*:}
  for tree in new old old new; do
    dir=$here; [ "$tree" = old ] && dir=$old
    n=$(find "$out" -name "${script}_${tree}.*.txt" | wc -l)
    # shellcheck disable=SC2086  # ARGS are words
    (cd "$dir" && PYTHONPATH=$dir "$here/.venv/bin/python" "bench/$script.py" $args > "$out/${script}_${tree}.$n.txt" 2>&1)
    echo "$script $tree run $n: $(tail -1 "$out/${script}_${tree}.$n.txt" | cut -c1-100)"
  done
done
