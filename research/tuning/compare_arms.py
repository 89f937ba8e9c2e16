"""Compare two settings' greedy evaluations situation by situation (research/tuning/ring_dqn.md).

Each arm is a set of run directories evaluated on the same evaluation seeds (their
``evaluation.json``). Per seed ("traffic situation") it takes each arm's success rate and caused
collision rate over its runs, and tests the mean of the differences (arm B minus arm A) with
:func:`der_ros.experiments.stats.paired_permutation_p`.

    python research/tuning/compare_arms.py --a RUN_DIR ... --b RUN_DIR ...
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from der_ros.experiments.stats import paired_permutation_p
from der_ros.train.eval_result import EvalResult


def per_situation(runs: list[Path]) -> tuple[list[int | None], np.ndarray, np.ndarray]:
    """Seeds, and per seed the success and caused-collision rates over ``runs``."""
    seeds: list[int | None] | None = None
    succ, caused = [], []
    for run in runs:
        eps = EvalResult.load(run / "evaluation.json").episodes
        s = [e.seed for e in eps]
        if seeds is None:
            seeds = s
        elif s != seeds:
            raise SystemExit(f"{run}: evaluated on other seeds than {runs[0]}")
        succ.append([e.outcome == "success" for e in eps])
        caused.append([e.outcome == "collision" and e.caused for e in eps])
    assert seeds is not None
    return seeds, np.mean(succ, axis=0), np.mean(caused, axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", nargs="+", type=Path, required=True, help="run directories of setting A")
    ap.add_argument("--b", nargs="+", type=Path, required=True, help="run directories of setting B")
    args = ap.parse_args()
    seeds_a, sa, ca = per_situation(args.a)
    seeds_b, sb, cb = per_situation(args.b)
    if seeds_a != seeds_b:
        raise SystemExit("the two arms were evaluated on different seeds")
    na, nb = len(args.a), len(args.b)
    for name, a, b in (("success", sa, sb), ("caused collision", ca, cb)):
        d = b - a
        print(f"{name}: A {a.mean():.4f} ({round(a.sum() * na)} in {len(a) * na}), "
              f"B {b.mean():.4f} ({round(b.sum() * nb)} in {len(b) * nb}); "
              f"situations B higher {int((d > 0).sum())}, lower {int((d < 0).sum())}, "
              f"p = {paired_permutation_p(d):.4f}")  # fmt: skip
    print(f"situations with a caused collision: A {int((ca > 0).sum())}, B {int((cb > 0).sum())}")


if __name__ == "__main__":
    main()
