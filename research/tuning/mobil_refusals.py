"""Why IDM+MOBIL misses exits: run the ``mobil`` baseline on the exit's tuning seeds and count, over the
missed episodes, the decisions where it kept its lane short of the exit lane by the reason a change
toward the exit was refused (research/tuning/exit_rules_mobil.md, notes).

    nice -n 10 python research/tuning/mobil_refusals.py --episodes 30

Reasons: ``rl_overlap`` / ``rf_overlap`` (the new leader / follower overlaps the ego), ``ego_brake``
(the ego would brake harder than b_safe behind its new leader), ``follower_brake`` (the new follower
would), ``incentive`` (safe, but the incentive did not exceed the threshold).
"""

from __future__ import annotations

import argparse
import collections

import gymnasium as gym

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.experiments.baselines import MOBIL_EGO_TYPE, rule_params
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE
from sumo_bridge.idm import idm_acceleration
from sumo_bridge.mobil import MobilParams, mobil_policy, situation_from_points


def _reasons(points, p: MobilParams) -> tuple[str, ...]:  # noqa: ANN001
    s = situation_from_points(points)
    rl, rf, out = s.right_leader, s.right_follower, []
    if rl is not None and rl.gap <= 0:
        out.append("rl_overlap")
    elif rl is not None and idm_acceleration(s.speed, rl.gap, rl.speed, p.idm) < -p.safe_decel:
        out.append("ego_brake")
    if rf is not None and rf.gap <= 0:
        out.append("rf_overlap")
    elif rf is not None and idm_acceleration(rf.speed, rf.gap, s.speed, p.idm) < -p.safe_decel:
        out.append("follower_brake")
    return tuple(out) or ("incentive",)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=30)
    args = ap.parse_args()
    p = rule_params("mobil", "exit")
    env = gym.make("der_ros/LaneChangeScenario-v0", scenario={"file": "exit", "ego_type": MOBIL_EGO_TYPE})
    reasons: collections.Counter[tuple[str, ...]] = collections.Counter()
    events: collections.Counter[str] = collections.Counter()
    last_lane: collections.Counter[int] = collections.Counter()
    try:
        for k in range(args.episodes):
            _, info = env.reset(seed=TUNING_EVAL_SEED_BASE + k)
            done, kept, lane = False, [], -1
            while not done:
                pts = info["points"]
                a = mobil_policy(pts, p)
                s = situation_from_points(pts)
                lane = s.lane
                if a == 0 and s.lane > s.target_lane >= 0:
                    kept.append(_reasons(pts, p))
                _, _, term, trunc, info = env.step(a)
                done = term or trunc
            events[info.get("event")] += 1
            if info.get("event") == "missed":
                reasons.update(kept)
                last_lane[lane] += 1
    finally:
        env.close()
    print(f"mobil {p}")
    print(f"{args.episodes} tuning episodes: {dict(events)}; lane at the miss: {dict(last_lane)}")
    for why, n in reasons.most_common():
        print(f"  {n:4d} decisions kept: {' + '.join(why)}")


if __name__ == "__main__":
    main()
