"""Greedy evaluation of trained runs on an unseeded reset stream: the reset distribution of training.

A seeded evaluation episode always builds the ring's traffic afresh; training resets mostly
re-place the last build's traffic (``ring_rebuild_every``). This runs each checkpoint for
``--episodes`` episodes of one stream (a seeded reset, then unseeded ones) and prints the outcome
counts, to check whether the caused-collision rate differs between the two (research/tuning/ring_dqn.md).

    python research/tuning/stream_eval.py RUN_DIR [RUN_DIR ...] [--episodes 6000] [--seed 1700000000]
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
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import GreedyQPolicy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    ap.add_argument("--episodes", type=int, default=6000)
    ap.add_argument("--seed", type=int, default=1_700_000_000, help="the stream's first seed (not a training seed)")
    args = ap.parse_args()
    total: collections.Counter[str] = collections.Counter()
    for run in args.runs:
        cfg = load_experiment_config(run / "config.yaml")
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        env = make_env_from_config(cfg.env, args.seed)
        try:
            policy = GreedyQPolicy(agent.q_net, np.float32)
            eps = run_episodes(policy, [env], [args.seed], args.episodes, episodes_per_seed=args.episodes)
        finally:
            env.close()
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        print(f"{run}: {dict(counts)}", flush=True)
    print(f"total over {len(args.runs)} runs: {dict(total)}")


if __name__ == "__main__":
    main()
