"""The shielded ring agents of ``der table3 --shield rss`` evaluated again, as one markdown table.

``research/shield/evals.sh`` writes ``<setting>/<method>.json`` with
``der evaluate --json``; this script reads them and prints, per setting and method, the episodes,
success, caused collisions with their exact 95% upper bound (recomputed here), time limits and the
shield's interventions per episode::

    python research/shield/eval_table.py runs/shield_eval
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from der_ros.experiments.evaluate_runs import upper_bound_95

#: setting folder -> what it is (docs/safety.md)
SETTINGS = {
    "on1000": "training traffic, shield on (report seeds)",
    "off300": "training traffic, the same agents with the shield off",
    "dense_on": "dense traffic (config/shift/ring_dense.yaml), shield on",
    "dense_off": "dense traffic, shield off",
    "careless_on": "less careful drivers (config/shift/ring_careless.yaml), shield on",
    "careless_off": "less careful drivers, shield off",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="the folder of <setting>/<method>.json (runs/shield_eval)")
    args = parser.parse_args()
    print("| setting | agents | runs x episodes | success | caused collisions | 95% upper bound | time limit | interventions / episode |")
    print("|---|---|---|---|---|---|---|---|")
    for setting, label in SETTINGS.items():
        for path in sorted((args.folder / setting).glob("*.json")):
            doc = json.loads(path.read_text())
            for method, row in doc["methods"].items():
                n, k = row["episodes"], row["caused_collisions"]
                print(f"| {label} | {method} | {row['runs']} x {n // row['runs']} | {row['success']:.3f} | {k} "
                      f"({k / n:.3f}) | {upper_bound_95(k, n):.2%} | {row['time_limit']:.3f} | "
                      f"{row['interventions_per_episode']:.1f} |")  # fmt: skip


if __name__ == "__main__":
    main()
