"""Evaluate baselines on the first N tuning evaluation seeds (what a sweep's runs are scored on).

The reference for research/tuning/ring_dqn.md's 1,800-episode comparisons: the tuned gap-acceptance
rule (and the other baselines) on the same tuning evaluation seeds (``TUNING_EVAL_SEED_BASE + k``)
as ``--set train.final_eval_episodes=N`` gives a sweep's runs. Prints success / caused collision /
time-limit counts per baseline.

    python research/tuning/baselines_tuning_seeds.py config/ring.yaml --baselines gap_acceptance sumo --episodes 1800

``--gap LEAD FOLLOW HEADWAY`` (repeatable) runs the gap-acceptance rule with other thresholds
instead of the tuned ones (config/baselines.yaml), to see where its caused collisions begin.
``--seed-set report`` runs on the report evaluation seeds (``EVAL_SEED_BASE + k``) instead, for a
setting already chosen on the tuning seeds; ``--out DIR`` also saves each evaluation as
``DIR/<name>[_<lead>_<follow>_<headway>]/evaluation.json`` for research/tuning/compare_arms.py.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.experiments.baselines import GapAcceptanceParams, evaluate_baseline, load_gap_params
from der_ros.train.config import load_experiment_config
from der_ros.train.eval_seeds import EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE
from sumo_bridge import ENV_NETWORKS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="training YAML whose env the baselines run on")
    ap.add_argument("--baselines", nargs="+", default=["gap_acceptance"])
    ap.add_argument("--episodes", type=int, default=1800)
    ap.add_argument(
        "--gap",
        nargs=3,
        type=float,
        action="append",
        metavar=("LEAD", "FOLLOW", "HEADWAY"),
        help="gap-acceptance thresholds to run instead of the tuned ones (repeatable; replaces --baselines)",
    )
    ap.add_argument("--seed-set", choices=("tuning", "report"), default="tuning",
                    help="tuning: TUNING_EVAL_SEED_BASE + k (default); report: EVAL_SEED_BASE + k")  # fmt: skip
    ap.add_argument("--out", type=Path, help="save DIR/<name>/evaluation.json per evaluation")
    args = ap.parse_args()
    seed_base = TUNING_EVAL_SEED_BASE if args.seed_set == "tuning" else EVAL_SEED_BASE
    cfg = load_experiment_config(args.config)
    net = ENV_NETWORKS.get(cfg.env.id)
    if net is None:
        raise SystemExit(f"{args.config}: env.id = {cfg.env.id!r} is not a SUMO lane-change env")
    runs = [(name, load_gap_params(net) if name == "gap_acceptance" else None) for name in args.baselines]
    if args.gap:
        if any(not v >= 0 for g in args.gap for v in g):
            raise SystemExit(f"--gap {args.gap}: expected thresholds >= 0")
        runs = [("gap_acceptance", GapAcceptanceParams(*g)) for g in args.gap]
    for name, gap in runs:
        res = evaluate_baseline(cfg.env, name, args.episodes, cfg.train.eval_episodes_per_seed, seed_base, gap)
        if args.out is not None:
            label = (
                name
                if gap is None or not args.gap
                else f"{name}_{gap.lead_gap:g}_{gap.follow_gap:g}_{gap.time_headway:g}"
            )
            (args.out / label).mkdir(parents=True, exist_ok=True)
            res.save(args.out / label / "evaluation.json")
        counts = collections.Counter("caused collision" if e.outcome == "collision" and e.caused else e.outcome
                                     for e in res.episodes)  # fmt: skip
        caused = [e.seed for e in res.episodes if e.outcome == "collision" and e.caused]
        print(
            f"{name}{'' if gap is None else ' ' + str(gap)}: {res.n} episodes, {dict(counts)}, mean return {res.mean_return:.2f}, "
            f"caused-collision seeds {caused}, {res.wall_s:.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
