"""SUMO environment benchmark: raw libsumo vs our env (libsumo) vs our env on traci, in one run.

* ``raw_steps_per_s``: ``libsumo.simulationStep()`` called directly on the ring scenario (same
  vehicles as the env places at reset; the env's subscriptions stay active, so this is the
  SUMO-side cost of one step);
* ``env_steps_per_s``: ``LaneChangeEnv.step`` with ``decision_interval=1`` (one SUMO step per env
  step) and a random policy, libsumo backend; only the time inside ``step`` counts;
* ``traci_env_steps_per_s``: the same env on the traci backend (sumo subprocess over a
  loopback socket);
* ``reset_ms``: mean ``reset()`` time on the ring (load + placement + 5 s warm-up);
* ``traci_getters_steps_per_s`` (peer): a plain traci loop reading the same quantities with one
  getter call each (neighbour getters, every vehicle's speed), i.e. without our subscriptions.

The two backends run one after the other (one libsumo simulation per process; traci closed
before). Then, unless ``--no-policies``, success/collision rates of scripted policies
(:mod:`sumo_bridge.policies`) on both networks with their default scenarios, which show the task
needs timing. Prints a table, then one JSON line.

    .venv/bin/python bench/sumo_env.py            # ~1-2 minutes
    .venv/bin/python bench/sumo_env.py --quick    # ~15 s
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from sumo_bridge.lane_change_env import LaneChangeEnv  # noqa: E402
from sumo_bridge.policies import RandomPolicy, gap_acceptance_policy, immediate_policy, keep_policy  # noqa: E402
from sumo_bridge.scenario import ScenarioConfig  # noqa: E402

BENCH_CFG = {"decision_interval": 1, "max_episode_steps": 100_000}


def raw_rate(steps: int, chunk: int = 1000) -> float:
    env = LaneChangeEnv(ScenarioConfig.ring(**BENCH_CFG))
    try:
        step = env.api.simulationStep
        elapsed, done, seed = 0.0, 0, 0
        while done < steps:
            env.reset(seed=seed)  # fresh traffic (routes are finite loops)
            seed += 1
            n = min(chunk, steps - done)
            t0 = time.perf_counter()
            for _ in range(n):
                step()
            elapsed += time.perf_counter() - t0
            done += n
        return steps / elapsed
    finally:
        env.close()


def env_rate(backend: str, steps: int) -> tuple[float, float]:
    """(env steps per second inside step(), mean reset ms) with a random policy."""
    env = LaneChangeEnv(ScenarioConfig.ring(backend=backend, **BENCH_CFG))
    rng = np.random.default_rng(0)
    step_time, reset_times, done = 0.0, [], 0
    try:
        t0 = time.perf_counter()
        env.reset(seed=0)
        reset_times.append(time.perf_counter() - t0)
        while done < steps:
            a = int(rng.integers(3)) if rng.random() < 0.05 else 0  # random, changing now and then
            t0 = time.perf_counter()
            _obs, _r, term, trunc, _info = env.step(a)
            step_time += time.perf_counter() - t0
            done += 1
            if term or trunc or done % 1000 == 0:
                t0 = time.perf_counter()
                env.reset()
                reset_times.append(time.perf_counter() - t0)
    finally:
        env.close()
    return done / step_time, 1000.0 * statistics.mean(reset_times)


def traci_getters_rate(steps: int) -> float:
    """Peer: traci with one getter call per quantity (no subscriptions), as a naive env would do.

    Per step: simulationStep, the six neighbour getters of the ego, the vehicle list, every
    vehicle's speed and the collision count (what our env reads through subscriptions).
    """
    env = LaneChangeEnv(ScenarioConfig.ring(backend="traci", **BENCH_CFG))
    try:
        v, sim = env.api.vehicle, env.api.simulation
        elapsed, done, seed = 0.0, 0, 0
        while done < steps:
            env.reset(seed=seed)
            seed += 1
            ego = env.ego_id
            n = min(500, steps - done)
            t0 = time.perf_counter()
            for _ in range(n):
                env.api.simulationStep()
                v.getLeader(ego, 30.0), v.getFollower(ego, 30.0)
                v.getLeftLeaders(ego), v.getLeftFollowers(ego), v.getRightLeaders(ego), v.getRightFollowers(ego)
                speeds = [v.getSpeed(x) for x in v.getIDList()]
                sim.getCollidingVehiclesNumber()
            elapsed += time.perf_counter() - t0
            done += n
            del speeds
        return steps / elapsed
    finally:
        env.close()


def evaluate(network: str, policy: Callable[[np.ndarray], int], episodes: int, seed: int) -> dict[str, float]:
    cfg = ScenarioConfig.ring() if network == "ring" else ScenarioConfig.urban()
    env = LaneChangeEnv(cfg)
    events: dict[str, int] = {"success": 0, "collision": 0, "time_limit": 0}
    returns = []
    try:
        _obs, info = env.reset(seed=seed)
        for ep in range(episodes):
            if ep:
                _obs, info = env.reset()
            total = 0.0
            while True:
                _obs, r, term, trunc, info = env.step(policy(info["points"]))
                total += r
                if term or trunc:
                    break
            events[info["event"]] += 1
            returns.append(total)
    finally:
        env.close()
    return {
        "success_rate": events["success"] / episodes,
        "collision_rate": events["collision"] / episodes,
        "time_limit_rate": events["time_limit"] / episodes,
        "mean_return": float(np.mean(returns)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps and episodes (a smoke run)")
    parser.add_argument("--no-policies", action="store_true", help="skip the scripted-policy success rates")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    n_raw, n_env, n_traci, episodes = (3000, 3000, 500, 30) if args.quick else (20000, 20000, 3000, 200)

    raw = raw_rate(n_raw)
    env_sps, reset_ms = env_rate("libsumo", n_env)
    traci_sps, traci_reset_ms = env_rate("traci", n_traci)
    getters_sps = traci_getters_rate(n_traci)
    print(f"{'measure':<34}{'value':>12}")
    print(f"{'raw libsumo simulationStep / s':<34}{raw:>12.0f}")
    print(f"{'env step / s (libsumo)':<34}{env_sps:>12.0f}   {env_sps / raw:.2f} x raw")
    print(f"{'env step / s (traci)':<34}{traci_sps:>12.0f}   libsumo is {env_sps / traci_sps:.1f} x traci")
    print(f"{'reset ms (libsumo / traci)':<34}{reset_ms:>12.2f}   {traci_reset_ms:.2f}")
    print(f"{'peer: traci with getters / s':<34}{getters_sps:>12.0f}   libsumo env is {env_sps / getters_sps:.1f} x")

    result: dict[str, object] = {
        "raw_steps_per_s": round(raw, 1),
        "env_steps_per_s": round(env_sps, 1),
        "traci_env_steps_per_s": round(traci_sps, 1),
        "reset_ms": round(reset_ms, 3),
        "env_over_raw": round(env_sps / raw, 3),
        "env_over_traci": round(env_sps / traci_sps, 2),
        "traci_getters_steps_per_s": round(getters_sps, 1),
        "env_over_traci_getters": round(env_sps / getters_sps, 2),
    }
    if not args.no_policies:
        policies: dict[str, Callable[[np.ndarray], int]] = {
            "immediate": immediate_policy,
            "random": RandomPolicy(seed=0),
            "gap_acceptance": gap_acceptance_policy,
            "keep": keep_policy,
        }
        table: dict[str, dict[str, dict[str, float]]] = {}
        print(f"\n{'network':<8}{'policy':<16}{'success':>9}{'collision':>11}{'time limit':>12}{'return':>9}  ({episodes} episodes)")
        for network in ("ring", "urban"):
            table[network] = {}
            for name, policy in policies.items():
                stats = evaluate(network, policy, episodes, seed=1234)
                table[network][name] = {k: round(v, 3) for k, v in stats.items()}
                print(f"{network:<8}{name:<16}{stats['success_rate']:>9.2f}{stats['collision_rate']:>11.2f}"
                      f"{stats['time_limit_rate']:>12.2f}{stats['mean_return']:>9.1f}")  # fmt: skip
        result["policies"] = table
    result["python"] = platform.python_version()
    try:
        from importlib.metadata import version

        result["sumo"] = version("eclipse-sumo")
    except Exception:
        pass
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
