"""What the gap rule would have done where a trained policy caused a collision (research/tuning/ring_dqn.md).

For each run directory (``config.yaml`` and ``checkpoint.pt``) and the evaluation seeds where that
run caused a collision (read from ``--evaluations DIR/<method>/<seed dir>/evaluation.json``, e.g.
research/run_files/table3_ring_h1_eval3000), replays the episode with the run's greedy policy and
prints the state at the decision where it commanded the lane change that collided: the gaps (m)
and relative speeds (m/s) of the target-side leader and follower, and whether the tuned
gap-acceptance rule (config/baselines.yaml) would have accepted that same gap, and which of three
kinds the state is (research/tuning/shield_eval.py's test): a target-side bumper-to-bumper gap
along the road is below 0 now ("overlap"), or one closes to below 0 within 1 s at constant speeds
("closes", what the 1 s near-gap channel reads as < 0), or "neither". Such states are not certain
collisions (research/tuning/change_kinds.py). Diagnosis only; nothing is tuned on it.

    python research/tuning/collision_states.py RUN_DIR [RUN_DIR ...] --evaluations DIR
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.experiments.baselines import load_gap_params
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_result import EvalResult
from sumo_bridge.observation import SLOT_NAMES
from sumo_bridge.policies import gap_acceptance_policy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from shield_eval import COL, blocked  # noqa: E402  (the shield's test of a target-side gap below 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    ap.add_argument("--evaluations", type=Path, required=True, help="DIR/<method>/<seed dir>/evaluation.json")
    args = ap.parse_args()
    gap = load_gap_params("ring")
    rows: list[bool] = []
    kinds: dict[str, int] = {}
    for run in args.runs:
        run = run.resolve()
        ev = EvalResult.load(args.evaluations / run.parent.name / run.name / "evaluation.json")
        bad = [e.seed for e in ev.episodes if e.outcome == "collision" and e.caused]
        if not bad:
            continue
        cfg = load_experiment_config(run / "config.yaml")
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        policy = GreedyQPolicy(agent.q_net, np.float32)
        env = make_env_from_config(cfg.env, int(bad[0]))
        try:
            for seed in bad:
                obs, info = env.reset(seed=int(seed))
                state = None
                for _ in range(10_000):
                    a = policy(np.asarray([obs]), [info])[0]
                    ego = info["points"][0]
                    if a != 0 and ego[COL["lane"]] != ego[COL["target_lane"]]:  # a change, not a no-op on the target
                        state = (info["points"].copy(), a)
                    obs, _, term, trunc, info = env.step(a)
                    if term or trunc or info.get("event") in ("success", "collision"):
                        break
                if info.get("event") != "collision" or state is None:
                    print(f"{run.name} seed {seed}: replay ended {info.get('event')!r}, not the saved collision")
                    continue
                points, a = state
                side = "left" if a == 1 else "right"
                lead = points[1 + SLOT_NAMES.index(f"{side}_leader")]
                foll = points[1 + SLOT_NAMES.index(f"{side}_follower")]
                rule = gap_acceptance_policy(points, gap.lead_gap, gap.follow_gap, gap.time_headway) != 0
                fmt = lambda p: (f"gap {p[COL['gap']]:6.2f} rel {p[COL['rel_speed']]:+5.2f}"  # noqa: E731
                                 if p[COL['present']] > 0.5 else "absent          ")  # fmt: skip
                kind = "overlap" if blocked(points, a, 0.0) else "closes" if blocked(points, a, 1.0) else "neither"
                kinds[kind] = kinds.get(kind, 0) + 1
                rows.append(rule)
                print(f"{run.parent.name}/{run.name} seed {seed}: leader {fmt(lead)} | follower {fmt(foll)} | "
                      f"{kind:7s} | gap rule would {'ACCEPT' if rule else 'reject'}", flush=True)  # fmt: skip
        finally:
            env.close()
    print(f"{len(rows)} collisions replayed; the gap rule would accept {sum(rows)} of those states; kinds {kinds}")


if __name__ == "__main__":
    main()
