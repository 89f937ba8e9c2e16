"""What the success-at-what-cost metrics cost the env (issue 44): ``info["imposed_brake"]`` and
``info["time_to_success"]`` (sumo_bridge/lane_change_env.py) against the same env with the per-step watch
switched off, in one process, in interleaved rounds (a shared machine's load drifts; medians reported).

The watch reads the ego's lane once per SUMO step only in a decision that commands a change (laneChangeMode
0) -- or at every step when SUMO's own model drives the ego (1621, the ``sumo`` baseline) -- and each
watched follower's acceleration once per step for 3 s after a change. Three settings:

* ``ring_gap``: ring.yaml's task (commit on success) under the tuned gap-acceptance rule;
* ``ring_random``: the ring under a random policy (a change in two of three decisions: the most watching);
* ``exit_sumo``: the exit scenario with SUMO's model driving the ego (the lane read at every step).

Then the time per call of the two getters the watch makes and of one ring SUMO step.

Rates are simulated SUMO steps per second inside ``env.step`` (resets excluded); a round is one seeded reset
(tuning seeds) and unseeded ones after it, the same episodes with and without the watch.

    .venv/bin/python bench/cost_metrics.py            # ~1 minute
    .venv/bin/python bench/cost_metrics.py --quick    # ~15 s
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
import timeit
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from der_ros.experiments.baselines import SUMO_DEFAULT_LANE_CHANGE_MODE, load_gap_params  # noqa: E402
from sumo_bridge.lane_change_env import LaneChangeEnv  # noqa: E402
from sumo_bridge.policies import gap_acceptance_policy  # noqa: E402
from sumo_bridge.scenario import ScenarioConfig  # noqa: E402
from sumo_bridge.scenario_file import scenario_from_kwargs  # noqa: E402


def _episodes(env: LaneChangeEnv, policy: Callable[[dict[str, Any]], int], seed: int, n: int) -> tuple[int, float, int]:
    """(SUMO steps, seconds inside step, lane changes seen) of ``n`` episodes: a seeded reset, then unseeded ones."""
    steps, elapsed, changes = 0, 0.0, 0
    di = env.config.decision_interval
    for k in range(n):
        _obs, info = env.reset(seed=seed) if k == 0 else env.reset()
        done = False
        while not done:
            a = policy(info)
            t0 = time.perf_counter()
            _obs, _r, terminated, truncated, info = env.step(a)
            elapsed += time.perf_counter() - t0
            steps += di * (1 + info.get("committed_steps", 0))
            done = terminated or truncated
        changes += info["lane_changes_done"]
    return steps, elapsed, changes


def _setting(name: str, cfg: ScenarioConfig, policy: Callable[[dict[str, Any]], int], rounds: int,
             per_round: int) -> dict[str, float]:  # fmt: skip
    env = LaneChangeEnv(cfg)
    watch = env._watch_followers
    on: list[float] = []
    off: list[float] = []
    changes = 0
    try:
        for k in range(rounds):
            for arm in ((True, False) if k % 2 == 0 else (False, True)):  # the same episodes both ways
                env._watch_followers = watch if arm else (lambda: None)  # type: ignore[method-assign]
                steps, seconds, seen = _episodes(env, policy, 1_500_000_000 + k, per_round)
                (on if arm else off).append(steps / seconds)
                if arm:
                    changes += seen
    finally:
        env.close()
    ratio = statistics.median(a / b for a, b in zip(on, off))
    return {"setting": name, "with_metrics_steps_per_s": statistics.median(on),
            "without_steps_per_s": statistics.median(off), "ratio": ratio,
            "lane_changes_per_episode": changes / (rounds * per_round)}  # fmt: skip


def _getter_us() -> dict[str, float]:
    """Microseconds per call (best of 3 x 20,000) of the watch's two getters, and of a ring SUMO step (x 500)."""
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        env.reset(seed=1)
        v, ego = env.api.vehicle, env.ego_id
        other = next(x for x in v.getIDList() if x != ego)
        calls = {"getAcceleration": (lambda: v.getAcceleration(other), 20_000),
                 "getLaneID": (lambda: v.getLaneID(ego), 20_000), "simulationStep": (env.api.simulationStep, 500)}  # fmt: skip
        return {name: 1e6 * min(timeit.repeat(f, number=n, repeat=3)) / n for name, (f, n) in calls.items()}
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rounds")
    args = parser.parse_args()
    rounds, per_round = (4, 5) if args.quick else (10, 10)
    gap = load_gap_params("ring")
    rng = np.random.default_rng(0)
    ring = ScenarioConfig.ring(commit_on_success=True)
    rows = [
        _setting("ring_gap", ring, lambda info: gap_acceptance_policy(info["points"], gap.lead_gap, gap.follow_gap,
                                                                      gap.time_headway), rounds, per_round),  # fmt: skip
        _setting("ring_random", ScenarioConfig.ring(), lambda info: int(rng.integers(3)), rounds, per_round),
        _setting("exit_sumo", scenario_from_kwargs("scenario", {"file": "exit",
                 "ego_lane_change_mode": SUMO_DEFAULT_LANE_CHANGE_MODE}), lambda info: 0, rounds, per_round),  # fmt: skip
    ]
    print("| setting | with metrics (SUMO steps/s) | without | ratio | lane changes / episode |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['setting']} | {r['with_metrics_steps_per_s']:.0f} | {r['without_steps_per_s']:.0f} "
              f"| {r['ratio']:.3f} | {r['lane_changes_per_episode']:.2f} |")  # fmt: skip
    us = _getter_us()
    print(", ".join(f"{name} {t:.2f} µs" for name, t in us.items()))
    print(json.dumps({"rounds": rounds, "episodes_per_round": per_round, "rows": rows, "call_us": us}))


if __name__ == "__main__":
    main()
