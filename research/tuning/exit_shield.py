"""The RSS shield on the exit scenario: old settings against the fleet-aware ones, on TUNING seeds only.

docs/safety.md, "The exit scenario". Every arm runs with exactly the shield parameters it names (the
scenario file's ``safety:`` section is *not* merged in here, so the old setting can be measured beside
the new one). Drivers: the rule baselines behind the shield (``immediate`` asks to change at every step,
``random`` draws all five actions, ``gap_acceptance`` the tuned rule) and, with ``--runs``, trained
checkpoints greedily. Seeds: TUNING_EVAL_SEED_BASE + k, never a report seed.

    python research/tuning/exit_shield.py --episodes 300 --arm old 0 9 0 --arm exit 33.33 7 1 \\
        [--drivers immediate random gap_acceptance] [--runs RUN_DIR ...]

An arm is NAME UNOBSERVED_SPEED BRAKE_MIN LANE_END (0/1) [BEYOND_LANE (0/1), default 0] [EGO_BRAKE, default 0 =
brake_min] (the unseen car brakes at unobserved_brake 9; the ring's other parameters: rho 0.1 s, accel_max 2.6,
brake_max 9). A run trained in mask
mode is evaluated in mask mode (greedy over the allowed actions), as its table row.
Targets commit 'exitshield' of der_ros (BEYOND_LANE: branch 'causec'; EGO_BRAKE: branch 'hole43').
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import time
from pathlib import Path

import numpy as np

import der_ros.safety.wrapper as shield_wrapper
from der_ros.agent.dqn import DQNAgent
from der_ros.experiments.baselines import baseline_policy, load_gap_params
from der_ros.safety.config import SafetyConfig
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE, evaluation_seeds

# every arm exactly as given: no merge with the scenario's safety section (research only)
shield_wrapper.scenario_shield = lambda cfg, scenario: cfg  # type: ignore[assignment]


def run(env_cfg, policy_for, episodes: int) -> tuple[collections.Counter, float, list[int]]:  # noqa: ANN001
    env = make_env_from_config(env_cfg, TUNING_EVAL_SEED_BASE)
    try:
        seeds = evaluation_seeds(episodes, TUNING_EVAL_SEED_BASE)
        eps = run_episodes(policy_for(int(env.action_space.n)), [env], seeds, episodes)
    finally:
        env.close()
    counts = collections.Counter("caused" if e.caused else e.outcome for e in eps)
    return counts, float(np.mean([e.interventions for e in eps])), [e.seed for e in eps if e.caused]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/exit.yaml")
    ap.add_argument("--episodes", type=int, default=300)
    ap.add_argument("--arm", nargs="+", action="append", required=True,
                    help="NAME UNOBSERVED_SPEED BRAKE_MIN LANE_END [BEYOND_LANE [EGO_BRAKE]]")
    ap.add_argument("--drivers", nargs="*", default=["immediate", "random", "gap_acceptance"])
    ap.add_argument("--runs", nargs="*", type=Path, default=[], help="run directories (config.yaml + checkpoint.pt)")
    args = ap.parse_args()
    cfg = load_experiment_config(args.config)
    gap = load_gap_params("exit")
    t0 = time.perf_counter()
    print(f"{args.config}, {args.episodes} tuning episodes (seeds {TUNING_EVAL_SEED_BASE}+k) per row")
    for arm in args.arm:
        if len(arm) not in (4, 5, 6):
            ap.error(f"--arm {' '.join(arm)}: expected NAME UNOBSERVED_SPEED BRAKE_MIN LANE_END [BEYOND_LANE [EGO_BRAKE]]")
    print("| driver | shield | unobserved_speed | brake_min | lane_end | beyond_lane | ego_brake | success | caused | "
          "time limit | missed | interventions/ep | caused seeds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    drivers = [(d, None) for d in args.drivers] + [(f"{r.parent.name}/{r.name}", r) for r in args.runs]
    for name, run_dir in drivers:
        for arm, unseen, bmin, lane_end, *rest in args.arm:
            beyond = rest[0] if rest else "0"
            ego_brake = rest[1] if len(rest) > 1 else "0"
            shield = SafetyConfig(kind="rss", unobserved_speed=float(unseen), brake_min=float(bmin),
                                  lane_end=bool(int(lane_end)), beyond_lane=bool(int(beyond)), ego_brake=float(ego_brake))
            if run_dir is None:
                env_cfg = dataclasses.replace(cfg.env, safety=shield)
                policy_for = lambda n, name=name: baseline_policy(name, gap, n_actions=n)  # noqa: E731
            else:
                run_env = load_experiment_config(run_dir / "config.yaml").env
                env_cfg = dataclasses.replace(run_env, safety=dataclasses.replace(run_env.safety, **{
                    k: getattr(shield, k) for k in ("unobserved_speed", "brake_min", "lane_end", "beyond_lane", "ego_brake")}))
                agent = DQNAgent.load(run_dir / "checkpoint.pt")
                agent.q_net.eval()
                use_mask = run_env.safety.mode == "mask"
                policy_for = lambda n, net=agent.q_net, m=use_mask: GreedyQPolicy(net, np.float32, use_mask=m)  # noqa: E731
            c, iv, bad = run(env_cfg, policy_for, args.episodes)
            print(f"| {name} | {arm} | {unseen} | {bmin} | {lane_end} | {beyond} | {ego_brake} | {c['success']} | {c['caused']} | {c['time_limit']} | "
                  f"{c['missed']} | {iv:.1f} | {bad} |", flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
