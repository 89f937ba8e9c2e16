"""Re-evaluate trained runs' final checkpoints greedily on more evaluation episodes.

A sweep's final evaluation has 300 episodes per run; when every run sits near 0 caused
collisions, that cannot tell two settings apart. This runs each checkpoint on the first
``--episodes`` tuning evaluation seeds (``TUNING_EVAL_SEED_BASE + k``, the seeds a sweep with
``train.final_eval_episodes = --episodes`` would use; the first 300 are the sweep's own) and
prints success / caused collision / time-limit counts per run and in total
(research/tuning/ring_dqn.md, sixth session). ``--seed-set report`` uses the report evaluation
seeds (``EVAL_SEED_BASE + k``) instead, for a finished report run that is no longer tuned; the
first 300 are then the table's own evaluation. ``--out DIR`` also saves each run's episodes as
``DIR/<method>/<seed dir>/evaluation.json``, which research/tuning/compare_arms.py reads.

    python research/tuning/reevaluate.py RUN_DIR [RUN_DIR ...] [--episodes 1800] \
        [--seed-set tuning|report] [--out DIR]
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.evaluation import (
    EVAL_SEED_BASE,
    TUNING_EVAL_SEED_BASE,
    EvalResult,
    GreedyQPolicy,
    evaluation_seeds,
    run_episodes,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    ap.add_argument("--episodes", type=int, default=1800)
    ap.add_argument("--seed-set", choices=("tuning", "report"), default="tuning",
                    help="tuning: TUNING_EVAL_SEED_BASE + k (default); report: EVAL_SEED_BASE + k")  # fmt: skip
    ap.add_argument("--out", type=Path, help="save DIR/<method>/<seed dir>/evaluation.json per run")
    args = ap.parse_args()
    base = EVAL_SEED_BASE if args.seed_set == "report" else TUNING_EVAL_SEED_BASE
    total: collections.Counter[str] = collections.Counter()
    for run in args.runs:
        cfg = load_experiment_config(run / "config.yaml")
        if cfg.train.eval_episodes_per_seed != 1:
            raise SystemExit(f"{run}: train.eval_episodes_per_seed = {cfg.train.eval_episodes_per_seed}, expected 1")
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        env = make_env_from_config(cfg.env, base)  # libsumo: one simulation per process
        try:
            seeds = evaluation_seeds(args.episodes, base)
            eps = run_episodes(GreedyQPolicy(agent.q_net, np.float32), [env], seeds, args.episodes)
        finally:
            env.close()
        if args.out is not None:
            dest = args.out / run.resolve().parent.name / run.resolve().name
            dest.mkdir(parents=True, exist_ok=True)
            EvalResult(step=-1, episodes=eps, seeds=seeds).save(dest / "evaluation.json")
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        bad = [e.seed for e in eps if e.caused]
        print(f"{run}: {args.episodes} episodes, success {counts['success']}, caused collision "
              f"{counts['caused_collision']} (seeds {bad}), time limit {counts['time_limit']}, "
              f"mean return {np.mean([e.ret for e in eps]):.2f}", flush=True)  # fmt: skip
    print(f"total over {len(args.runs)} runs: {dict(total)}")


if __name__ == "__main__":
    main()
