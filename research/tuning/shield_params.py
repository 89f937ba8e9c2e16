"""Choose the RSS shield's parameters on TUNING seeds (docs/safety.md, "Choosing the parameters").

The most permissive driver behind a shield is one that asks to change lane at every step
(sumo_bridge.policies.immediate_policy): behind the shield it changes exactly when the shield
allows. Its caused collisions measure what the shield lets through, its success how much the
shield forbids. For each setting this runs that driver behind ``safety.kind: rss`` on the first
``--episodes`` tuning evaluation seeds (TUNING_EVAL_SEED_BASE + k, never a report seed) of a
network and prints one row; the shipped defaults are the most permissive setting with 0 caused
collisions on both networks. The gap rule (config/baselines.yaml) is printed beside it on the
same episodes.

    python research/tuning/shield_params.py --network ring --episodes 200
"""

from __future__ import annotations

import argparse
import collections
import itertools
import time

import numpy as np

from der_ros.configuration import from_dict, to_dict
from der_ros.experiments.baselines import baseline_policy, load_gap_params
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE, evaluation_seeds

GRID = {  # response_time (s), accel_max, brake_min, brake_max (m/s^2)
    "response_time": (0.1, 0.25, 0.5, 1.0),
    "accel_max": (0.0, 1.0, 2.6),
    "brake_min": (4.5, 9.0),
    "brake_max": (9.0,),
}


def evaluate(env_cfg: EnvConfig, policy_name: str, episodes: int, per_seed: int, gap=None) -> tuple[dict, float]:  # noqa: ANN001
    env = make_env_from_config(env_cfg, TUNING_EVAL_SEED_BASE)
    try:
        seeds = evaluation_seeds(-(-episodes // per_seed), TUNING_EVAL_SEED_BASE)
        eps = run_episodes(baseline_policy(policy_name, gap), [env], seeds, episodes, per_seed)
    finally:
        env.close()
    counts = collections.Counter("caused" if e.caused else e.outcome for e in eps)
    return counts, float(np.mean([e.interventions for e in eps]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", choices=("ring", "urban"), default="ring")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--only", nargs=4, type=float, metavar=("RHO", "ACC", "BMIN", "BMAX"), action="append",
                    help="evaluate only these settings (repeatable) instead of the grid")
    args = ap.parse_args()
    cfg = load_experiment_config(f"config/{args.network}.yaml")
    per_seed = cfg.train.eval_episodes_per_seed
    gap = load_gap_params(args.network)
    t0 = time.perf_counter()
    counts, _ = evaluate(cfg.env, "gap_acceptance", args.episodes, per_seed, gap)
    print(f"{args.network}, {args.episodes} tuning episodes; gap rule (unshielded): success {counts['success']}, "
          f"caused {counts['caused']}, time limit {counts['time_limit']}", flush=True)
    print("| rho | accel_max | brake_min | brake_max | success | caused | time limit | interventions/ep |")
    print("|---|---|---|---|---|---|---|---|")
    settings = args.only or list(itertools.product(*GRID.values()))
    for rho, acc, bmin, bmax in settings:
        shield = {"kind": "rss", "response_time": rho, "accel_max": acc, "brake_min": bmin, "brake_max": bmax}
        env_cfg = from_dict(EnvConfig, {**to_dict(cfg.env), "safety": shield})
        counts, iv = evaluate(env_cfg, "immediate", args.episodes, per_seed)
        print(f"| {rho} | {acc} | {bmin} | {bmax} | {counts['success']} | {counts['caused']} | {counts['time_limit']} "
              f"| {iv:.1f} |", flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
