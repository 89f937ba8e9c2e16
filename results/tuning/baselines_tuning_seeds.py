"""Evaluate baselines on the first N tuning evaluation seeds (what a sweep's runs are scored on).

The reference for results/tuning/ring_dqn.md's 1,800-episode comparisons: the tuned gap-acceptance
rule (and the other baselines) on the same tuning evaluation seeds (``TUNING_EVAL_SEED_BASE + k``)
as ``--set train.final_eval_episodes=N`` gives a sweep's runs. Prints success / caused collision /
time-limit counts per baseline.

    python results/tuning/baselines_tuning_seeds.py config/ring.yaml --baselines gap_acceptance sumo --episodes 1800
"""

from __future__ import annotations

import argparse
import collections

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.experiments.baselines import _network, evaluate_baseline, load_gap_params
from der_ros.train.config import load_experiment_config
from der_ros.train.evaluation import TUNING_EVAL_SEED_BASE


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="training YAML whose env the baselines run on")
    ap.add_argument("--baselines", nargs="+", default=["gap_acceptance"])
    ap.add_argument("--episodes", type=int, default=1800)
    args = ap.parse_args()
    cfg = load_experiment_config(args.config)
    net = _network(cfg.env)
    if net is None:
        raise SystemExit(f"{args.config}: env.id = {cfg.env.id!r} is not a SUMO lane-change env")
    for name in args.baselines:
        gap = load_gap_params(net) if name == "gap_acceptance" else None
        res = evaluate_baseline(
            cfg.env, name, args.episodes, cfg.train.eval_episodes_per_seed, TUNING_EVAL_SEED_BASE, gap
        )
        counts = collections.Counter("caused collision" if e.outcome == "collision" and e.caused else e.outcome
                                     for e in res.episodes)  # fmt: skip
        caused = [e.seed for e in res.episodes if e.outcome == "collision" and e.caused]
        print(
            f"{name}: {res.n} episodes, {dict(counts)}, mean return {res.mean_return:.2f}, "
            f"caused-collision seeds {caused}, {res.wall_s:.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
