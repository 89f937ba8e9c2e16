"""How often does a greedy ring policy change lanes into each kind of state, and with what outcome?

Counterpart of research/tuning/collision_states.py: it replays the first ``EPISODES`` report
evaluation situations (``EVAL_SEED_BASE + k``) with each run's greedy policy and classifies the
state of the last lane change each episode commanded, with the shield test of
research/tuning/shield_eval.py: a target-side gap < 0 now ("overlap"), < 0 within 1 s at constant
speeds ("closes"), or neither; and whether the tuned gap rule (config/baselines.yaml) would have
changed there too ("rule accepts" / "rule rejects"). It prints the counts per (outcome, kind, rule)
for each run and summed over the runs: whether those kinds are collisions waiting to happen or
mostly safe (the other vehicle brakes, or the along-road gap on the curved ring is not a lateral
overlap), i.e. what collision risk the policy takes when it changes where the rule would not.

    python research/tuning/change_kinds.py EPISODES RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.experiments.baselines import load_gap_params
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_seeds import EVAL_SEED_BASE
from sumo_bridge.policies import gap_acceptance_policy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from shield_eval import COL, blocked  # noqa: E402


def classify(run: Path, n: int) -> collections.Counter[tuple[str, str, str]]:
    """(outcome, kind, rule) counts of the last commanded change over the first ``n`` report situations."""
    cfg = load_experiment_config(run / "config.yaml")
    agent = DQNAgent.load(run / "checkpoint.pt")
    agent.q_net.eval()
    policy = GreedyQPolicy(agent.q_net, np.float32)
    rule = load_gap_params("ring")
    env = make_env_from_config(cfg.env, EVAL_SEED_BASE)
    counts: collections.Counter[tuple[str, str, str]] = collections.Counter()
    try:
        for k in range(n):
            obs, info = env.reset(seed=EVAL_SEED_BASE + k)
            state = None
            while True:
                a = policy(np.asarray([obs]), [info])[0]
                ego = info["points"][0]
                if a != 0 and ego[COL["lane"]] != ego[COL["target_lane"]]:
                    state = (info["points"].copy(), a)
                obs, _, term, trunc, info = env.step(a)
                if term or trunc or info.get("event") in ("success", "collision"):
                    break
            if state is not None:
                points, a = state
                kind = "overlap" if blocked(points, a, 0.0) else "closes" if blocked(points, a, 1.0) else "neither"
                accepts = gap_acceptance_policy(points, rule.lead_gap, rule.follow_gap, rule.time_headway) == a
                counts[(str(info.get("event", "time_limit")), kind, "rule accepts" if accepts else "rule rejects")] += 1
    finally:
        env.close()
    return counts


def _print(title: str, counts: collections.Counter[tuple[str, str, str]]) -> None:
    print(f"{title}; (outcome, kind of the last change's state, gap rule): count")
    for key, c in sorted(counts.items()):
        print(f"  {key}: {c}")


def main() -> None:
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    n, runs = int(sys.argv[1]), [Path(r) for r in sys.argv[2:]]
    total: collections.Counter[tuple[str, str, str]] = collections.Counter()
    for run in runs:
        counts = classify(run, n)
        total.update(counts)
        _print(f"{run}: {n} episodes", counts)
    if len(runs) > 1:
        _print(f"total over {len(runs)} runs, {n * len(runs)} episodes", total)


if __name__ == "__main__":
    main()
