"""The exit's baseline table from the evaluations ``der baselines`` cached, with every collision of the ego
beside the caused ones (SUMO's own lane changes are never counted as caused: docs/scenarios.md).

    der baselines config/exit.yaml --episodes 300 --jobs 1 --out OUT
    python research/tuning/exit_table.py OUT/exit
"""

from __future__ import annotations

import argparse
from pathlib import Path

from der_ros.experiments.baselines import EXIT_BASELINES
from der_ros.train.eval_result import EvalResult


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="der baselines' --out folder of the network (OUT/exit)")
    args = ap.parse_args()
    print("| baseline | episodes | success | missed | caused collision | any collision of the ego | time limit | mean return |")
    print("|---|---|---|---|---|---|---|---|")
    for name in EXIT_BASELINES:
        path = args.folder / name / "evaluation.json"
        if not path.is_file():
            continue
        r = EvalResult.load(path)
        print(f"| `{name}` | {r.n} | {r.success_rate:.3f} | {r.rate('missed'):.3f} | {r.collision_rate:.3f} "
              f"| {r.rate('collision'):.3f} | {r.time_limit_rate:.3f} | {r.mean_return:.2f} |")


if __name__ == "__main__":
    main()
