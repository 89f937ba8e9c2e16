"""Re-evaluate trained runs' final checkpoints greedily on more tuning evaluation episodes.

A sweep's final evaluation has 300 episodes per run; when every run sits near 0 caused
collisions, that cannot tell two settings apart. This runs each checkpoint on the first
``--episodes`` tuning evaluation seeds (``TUNING_EVAL_SEED_BASE + k``, the seeds a sweep with
``train.final_eval_episodes = --episodes`` would use; the first 300 are the sweep's own) and
prints success / caused collision / time-limit counts per run and in total
(results/tuning/ring_dqn.md, sixth session).

    python results/tuning/reevaluate.py RUN_DIR [RUN_DIR ...] [--episodes 1800]
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
from der_ros.train.evaluation import TUNING_EVAL_SEED_BASE, GreedyQPolicy, evaluation_seeds, run_episodes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    ap.add_argument("--episodes", type=int, default=1800)
    args = ap.parse_args()
    total: collections.Counter[str] = collections.Counter()
    for run in args.runs:
        cfg = load_experiment_config(run / "config.yaml")
        if cfg.train.eval_episodes_per_seed != 1:
            raise SystemExit(f"{run}: train.eval_episodes_per_seed = {cfg.train.eval_episodes_per_seed}, expected 1")
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        env = make_env_from_config(cfg.env, TUNING_EVAL_SEED_BASE)  # libsumo: one simulation per process
        try:
            seeds = evaluation_seeds(args.episodes, TUNING_EVAL_SEED_BASE)
            eps = run_episodes(GreedyQPolicy(agent.q_net, np.float32), [env], seeds, args.episodes)
        finally:
            env.close()
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        bad = [e.seed for e in eps if e.caused]
        print(f"{run}: {args.episodes} episodes, success {counts['success']}, caused collision "
              f"{counts['caused_collision']} (seeds {bad}), time limit {counts['time_limit']}, "
              f"mean return {np.mean([e.ret for e in eps]):.2f}", flush=True)  # fmt: skip
    print(f"total over {len(args.runs)} runs: {dict(total)}")


if __name__ == "__main__":
    main()
