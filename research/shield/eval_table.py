"""The shielded ring agents of ``der table3 --shield rss`` evaluated again, as one markdown table.

``research/shield/evals.sh`` writes ``<setting>/<method>.json`` with
``der evaluate --json``; this script reads them and prints, per setting and method, the episodes,
success, caused collisions with their exact 95% upper bound (recomputed here), time limits and the
shield's interventions per episode::

    python research/shield/eval_table.py runs/shield_eval [--out results/shield_ring_evaluations.md]
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
    parser.add_argument("--out", type=Path, help="also write the table, with a header naming the commands, to this file")
    args = parser.parse_args()
    lines = table(args.folder)
    print("\n".join(lines))
    if args.out is not None:
        head = [
            "# The shielded ring agents, evaluated again",
            "",
            "The agents of Table 3's shielded rows (`der table3 --shield rss`, run files in",
            "`research/run_files/table3/ring/<method>+shield/`), each final checkpoint evaluated greedily on report",
            "seeds by `der evaluate`: behind the shield, with the shield taken off, and under the two shifted",
            "traffic settings of `config/shift/` (docs/safety.md, \"What was measured\"). Made with",
            "",
            "```bash",
            "research/shield/evals.sh runs/table3/ring runs/shield_eval",
            f"python research/shield/eval_table.py runs/shield_eval --out {args.out}",
            "```",
            "",
            "The upper bound is the exact (Clopper-Pearson) one-sided 95% bound of the caused-collision rate.",
            "",
        ]
        args.out.write_text("\n".join(head + lines) + "\n")


def table(folder: Path) -> list[str]:
    """The markdown rows of every ``<setting>/<method>.json`` under ``folder``."""
    lines = ["| setting | agents | runs x episodes | success | caused collisions | 95% upper bound | time limit | interventions / episode |"]
    lines.append("|---|---|---|---|---|---|---|---|")
    for setting, label in SETTINGS.items():
        for path in sorted((folder / setting).glob("*.json")):
            doc = json.loads(path.read_text())
            for method, row in doc["methods"].items():
                n, k = row["episodes"], row["caused_collisions"]
                lines.append(f"| {label} | {method} | {row['runs']} x {n // row['runs']} | {row['success']:.3f} | {k} "
                      f"({k / n:.3f}) | {upper_bound_95(k, n):.2%} | {row['time_limit']:.3f} | "
                      f"{row['interventions_per_episode']:.1f} |")  # fmt: skip
    return lines


if __name__ == "__main__":
    main()
