"""How many decisions after its lane change does a caused collision happen? (research/tuning/ring_dqn.md)

Runs the immediate-change baseline (``sumo_bridge.policies.immediate_policy``) on ring
episodes with seeds 1,700,000,000 + k, outside the training, tuning and report seed sets, and
counts the decisions between the change and each caused collision.

    python research/tuning/collision_delay.py [--episodes 200] [--config config/ring.yaml]
"""

from __future__ import annotations

import argparse
import collections

import gymnasium as gym

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.train.config import load_experiment_config
from sumo_bridge.policies import immediate_policy

SEED_BASE = 1_700_000_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--config", default="config/ring.yaml")
    args = ap.parse_args()
    cfg = load_experiment_config(args.config)
    env = gym.make(cfg.env.id, **cfg.env.kwargs)
    delays: collections.Counter[int] = collections.Counter()
    uncaused = 0
    for k in range(args.episodes):
        _, info = env.reset(seed=SEED_BASE + k)
        t, change_t = 0, None
        while True:
            action = immediate_policy(info["points"])
            if change_t is None and action != 0:
                change_t = t
            _, _, terminated, truncated, info = env.step(action)
            if info.get("event") == "collision":
                if info.get("caused"):
                    delays[t - change_t] += 1
                else:
                    uncaused += 1
            if terminated or truncated:
                break
            t += 1
    env.close()
    print(f"{args.episodes} episodes: {sum(delays.values())} caused collisions, "
          f"decisions after the change -> count: {dict(sorted(delays.items()))}; {uncaused} not caused")


if __name__ == "__main__":
    main()
