"""Tune the exit's rule baselines on the tuning seeds: IDM+MOBIL (``mobil``) and SUMO's model with tuned
lane-change parameters (``sumo_tuned``); a small grid each, scored on the *tuning* evaluation seeds
(``TUNING_EVAL_SEED_BASE + k``), never on the report seeds.

    nice -n 10 python research/tuning/exit_rules.py config/exit.yaml --rule sumo_tuned --episodes 120 \\
        --out /work/wt/_scratch/exitbase/tune --md research/tuning/exit_rules_sumo_tuned.md
    nice -n 10 python research/tuning/exit_rules.py config/exit.yaml --rule mobil --episodes 120 ...

Best = the highest success among settings without a collision (ties: higher return). ``mobil``
counts the collisions the env attributes to the ego's commanded changes (caused, as for the gap
rule); ``sumo_tuned`` counts every collision of the ego, since SUMO's own changes are not commanded
and the env attributes none of them. The pick is copied by hand into ``config/baselines.yaml``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import itertools
import subprocess
from pathlib import Path
from typing import Any

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.experiments.baselines import _network, baseline_job, run_baselines
from der_ros.train.config import load_experiment_config
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE
from sumo_bridge.mobil import MobilParams

#: the grids: SUMO LC2013 parameters of the ego (defaults 1 / 1 / 1) and MOBIL's exit bias and b_safe
#: (politeness 0.5, threshold 0.2 m/s^2, exit_lookahead 100 m stay at their defaults)
GRIDS: dict[str, dict[str, tuple[float, ...]]] = {
    "sumo_tuned": {"lcAssertive": (1.0, 2.0, 3.0, 5.0), "lcStrategic": (1.0, 3.0), "lcCooperative": (1.0, 0.5)},
    "mobil": {"exit_bias": (1.0, 3.0, 10.0, 30.0), "safe_decel": (4.0, 6.0, 9.0)},
}


def _params(rule: str, combo: dict[str, float]) -> Any:
    return dataclasses.replace(MobilParams(), **combo) if rule == "mobil" else dict(combo)


def _collisions(rule: str, r: EvalResult) -> float:
    return r.collision_rate if rule == "mobil" else r.rate("collision")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="the exit's experiment YAML (config/exit.yaml)")
    ap.add_argument("--rule", choices=tuple(GRIDS), required=True)
    ap.add_argument("--episodes", type=int, default=120, help="tuning episodes per setting")
    ap.add_argument("--out", type=Path, required=True, help="folder of the cached evaluations")
    ap.add_argument("--md", type=Path, required=True, help="markdown table to write")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    cfg = load_experiment_config(args.config)
    net = _network(cfg.env)
    grid = GRIDS[args.rule]
    combos = [dict(zip(grid, values)) for values in itertools.product(*grid.values())]
    jobs = [baseline_job(cfg.env, args.rule, args.episodes, cfg.train.eval_episodes_per_seed, TUNING_EVAL_SEED_BASE,
                         args.out / args.rule / "_".join(f"{k}{v:g}" for k, v in c.items()), _params(args.rule, c))
            for c in combos]  # fmt: skip
    results = run_baselines(jobs, args.jobs)
    scored = [(c, results[j.out_dir]) for c, j in zip(combos, jobs)]
    safe = [s for s in scored if _collisions(args.rule, s[1]) == 0.0] or scored
    best = max(safe, key=lambda s: (s[1].success_rate, s[1].mean_return))[0]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    counted = "caused collisions" if args.rule == "mobil" else "any collision of the ego"
    lines = [f"# {args.rule} on {net}: tuning", "",
             f"{args.episodes} episodes per setting on the tuning evaluation seeds ({TUNING_EVAL_SEED_BASE} + k); "
             f"best = the highest success with no collision ({counted}); ties: higher return. "
             f"{datetime.date.today()}, commit {commit}.", "",
             "```", f"nice -n 10 python research/tuning/exit_rules.py {args.config} --rule {args.rule} "
             f"--episodes {args.episodes} --out OUT --md {args.md}", "```", "",
             f"Best: `{best}`", "",
             "| " + " | ".join(grid) + " | success | missed | caused collision | any collision | time limit | return |",
             "|" + "---|" * (len(grid) + 6)]  # fmt: skip
    for c, r in sorted(scored, key=lambda s: (-s[1].success_rate, -s[1].mean_return)):
        lines.append("| " + " | ".join(f"{v:g}" for v in c.values()) + f" | {r.success_rate:.3f} | {r.rate('missed'):.3f} "
                     f"| {r.collision_rate:.3f} | {r.rate('collision'):.3f} | {r.time_limit_rate:.3f} "
                     f"| {r.mean_return:.2f} |")  # fmt: skip
    args.md.parent.mkdir(parents=True, exist_ok=True)
    args.md.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
