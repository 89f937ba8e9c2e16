"""Evaluate trained ring policies behind an overlap shield (a what-if for a safety layer; not DQN or DER).

The shield replaces a commanded lane change by "keep lane" when a target-side vehicle (leader or
follower on the side of the change) overlaps the ego now (gap < 0) or would within ``--horizon``
seconds at constant speeds (leader: gap + rel_speed * h < 0; follower: gap - rel_speed * h < 0).
Everything else is the run's greedy policy. Each run's final checkpoint is evaluated on the first
``--episodes`` report evaluation seeds (``EVAL_SEED_BASE + k``) and saved as
``--out DIR/<method>/<seed dir>/evaluation.json`` for research/tuning/compare_arms.py
(research/run_files/table3_ring_h1_eval3000/README.md, last section).

    python research/tuning/shield_eval.py RUN_DIR [RUN_DIR ...] --out DIR [--episodes 3000] [--horizon 1.0]
"""

from __future__ import annotations

import argparse
import collections
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import EVAL_SEED_BASE, evaluation_seeds
from sumo_bridge.observation import POINT_FIELDS, SLOT_NAMES

COL = {name: i for i, name in enumerate(POINT_FIELDS)}
ROW = {name: 1 + i for i, name in enumerate(SLOT_NAMES)}
SIDE = {1: "left", 2: "right"}  # action -> side of the change (sumo_bridge.policies)


def blocked(points: np.ndarray, action: int, horizon: float) -> bool:
    """True if a target-side vehicle overlaps the ego now or within ``horizon`` seconds."""
    side = SIDE.get(action)
    if side is None:
        return False
    for slot, sign in ((f"{side}_leader", 1.0), (f"{side}_follower", -1.0)):
        p = points[ROW[slot]]
        if p[COL["present"]] > 0.5 and min(p[COL["gap"]], p[COL["gap"]] + sign * p[COL["rel_speed"]] * horizon) < 0:
            return True
    return False


class ShieldedPolicy:
    """The greedy policy with changes into an overlap replaced by keep; counts the overrides."""

    def __init__(self, greedy: GreedyQPolicy, horizon: float) -> None:
        self.greedy, self.horizon, self.overrides = greedy, horizon, 0

    def __call__(self, obs: np.ndarray, infos: Sequence[dict[str, Any]]) -> list[int]:
        out = []
        for a, info in zip(self.greedy(obs, infos), infos):
            if blocked(info["points"], a, self.horizon):
                self.overrides += 1
                a = 0
            out.append(a)
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    ap.add_argument("--out", type=Path, required=True, help="save DIR/<method>/<seed dir>/evaluation.json per run")
    ap.add_argument("--episodes", type=int, default=3000)
    ap.add_argument("--horizon", type=float, default=1.0, help="seconds of look-ahead of the shield (>= 0)")
    args = ap.parse_args()
    if not args.horizon >= 0:
        raise SystemExit(f"--horizon = {args.horizon}: expected a number >= 0")
    total: collections.Counter[str] = collections.Counter()
    for run in args.runs:
        run = run.resolve()
        cfg = load_experiment_config(run / "config.yaml")
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        policy = ShieldedPolicy(GreedyQPolicy(agent.q_net, np.float32), args.horizon)
        env = make_env_from_config(cfg.env, EVAL_SEED_BASE)  # libsumo: one simulation per process
        try:
            seeds = evaluation_seeds(args.episodes, EVAL_SEED_BASE)
            eps = run_episodes(policy, [env], seeds, args.episodes)
        finally:
            env.close()
        dest = args.out / run.parent.name / run.name
        dest.mkdir(parents=True, exist_ok=True)
        EvalResult(step=-1, episodes=eps, seeds=seeds).save(dest / "evaluation.json")
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        print(f"{run.parent.name}/{run.name}: {args.episodes} episodes, success {counts['success']}, caused collision "
              f"{counts['caused_collision']}, time limit {counts['time_limit']}, shield overrides {policy.overrides}",
              flush=True)  # fmt: skip
    print(f"total over {len(args.runs)} runs: {dict(total)}")


if __name__ == "__main__":
    main()
