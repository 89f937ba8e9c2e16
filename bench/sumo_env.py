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
  getter call each (neighbour getters, every vehicle's speed), i.e. without our subscriptions;
* ``raw_over_traci``: raw libsumo steps/s over traci env steps/s, the ceiling of
  ``env_over_traci`` (what an env with no per-step work at all beside the simulation step would
  reach on this machine);
* ``commit_env_vs_raw``: the commit step (ring.yaml's task: ``commit_on_success``, the change's
  transition simulates the rest of the 50-decision horizon) against raw libsumo stepping the same
  simulated time with the same reads, in simulated steps per second. The env side is the time
  inside the ``step`` that commits (the change's decision plus the fast-forward), over episodes where
  the gap-acceptance policy's change succeeds; the raw side starts from the same seeded state and
  runs, per SUMO step, ``simulationStep()`` and the collision count, and per decision every
  vehicle's speed and their mean (the reward's reads), nothing else (the ego's context
  subscription dropped). The speeds are read both ways libsumo offers -- the env's speed
  subscriptions (``getAllSubscriptionResults``) and getters (``getIDList`` + ``getSpeed``) -- and
  the faster of the two per round is the peer (``commit_raw_reads``: which one won). Each commit is
  followed by the raw runs on its seed and length, so a pair shares the machine's load;
* ``default_*``: the same libsumo / traci comparison at the scenario's default
  ``decision_interval`` (5 SUMO steps per decision, what training uses), in simulated steps per
  second so it compares with ``raw_steps_per_s``.

All four are measured in interleaved rounds (the load of a shared machine drifts); the medians
of the per-round rates and ratios are reported. The traci env runs beside the libsumo one (its
SUMO is a subprocess; only a second *libsumo* simulation is refused). Then, unless ``--no-policies``, success/collision rates of scripted policies
(:mod:`sumo_bridge.policies`) on both networks with their default scenarios, which show the task
needs timing. Prints a table, then one JSON line.

    .venv/bin/python bench/sumo_env.py            # ~1-2 minutes
    .venv/bin/python bench/sumo_env.py --quick    # ~15 s
    .venv/bin/python bench/sumo_env.py --exit     # the exit scenario only (issue 44)
    .venv/bin/python bench/sumo_env.py --commit-only   # the commit step against raw libsumo, ~30 s
"""

from __future__ import annotations

import argparse
import json
import logging
import math
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


def _chunk_env(env: LaneChangeEnv, steps: int, rng: np.random.Generator, seed: int) -> float:
    """Seconds inside ``env.step`` for ``steps`` steps of a mostly-keep, sometimes random policy."""
    env.reset(seed=seed)
    elapsed = 0.0
    for _ in range(steps):
        a = int(rng.integers(3)) if rng.random() < 0.05 else 0
        t0 = time.perf_counter()
        _obs, _r, term, trunc, _info = env.step(a)
        elapsed += time.perf_counter() - t0
        if term or trunc:
            env.reset()
    return elapsed


def _chunk_raw(env: LaneChangeEnv, steps: int, seed: int) -> float:
    env.reset(seed=seed)  # same vehicles as the env places; its subscriptions stay active
    step = env.api.simulationStep
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return time.perf_counter() - t0


def _chunk_getters(env: LaneChangeEnv, steps: int, seed: int) -> float:
    """Peer: traci with one getter call per quantity (no subscriptions), as a naive env would do.

    Per step: simulationStep, the six neighbour getters of the ego, the vehicle list, every
    vehicle's speed and the collision count (what our env reads through subscriptions).
    """
    env.reset(seed=seed)
    v, sim, ego = env.api.vehicle, env.api.simulation, env.ego_id
    t0 = time.perf_counter()
    for _ in range(steps):
        env.api.simulationStep()
        v.getLeader(ego, 30.0), v.getFollower(ego, 30.0)
        v.getLeftLeaders(ego), v.getLeftFollowers(ego), v.getRightLeaders(ego), v.getRightFollowers(ego)
        _speeds = [v.getSpeed(x) for x in v.getIDList()]
        sim.getCollidingVehiclesNumber()
    return time.perf_counter() - t0


def _reset_ms(env: LaneChangeEnv, n: int) -> float:
    env.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(n):
        env.reset()
    return 1000.0 * (time.perf_counter() - t0) / n


def _rounds(overrides: dict[str, int], rounds: int, chunk: int, traci_chunk: int, rng: np.random.Generator,
            *, with_peers: bool) -> dict[str, list[float]]:  # fmt: skip
    """Per-round rates in *simulated* steps per second of raw libsumo, the libsumo env and the
    traci env on the ring with ``overrides`` (plus, ``with_peers``, the traci-getters loop and
    the reset times). Interleaved: the machine's load drifts, so each round measures all of them
    back to back. The two envs live side by side (traci runs SUMO in a subprocess; only a second
    libsumo simulation is refused)."""
    lib = LaneChangeEnv(ScenarioConfig.ring(**overrides))
    tra = LaneChangeEnv(ScenarioConfig.ring(backend="traci", **overrides))
    di = lib.config.decision_interval
    out: dict[str, list[float]] = {"raw": [], "env": [], "traci": [], "getters": []}
    try:
        for k in range(rounds):
            out["raw"].append(chunk / _chunk_raw(lib, chunk, seed=k))
            out["env"].append(chunk // di * di / _chunk_env(lib, chunk // di, rng, seed=k))
            out["traci"].append(traci_chunk // di * di / _chunk_env(tra, traci_chunk // di, rng, seed=k))
            if with_peers:
                out["getters"].append(traci_chunk / _chunk_getters(tra, traci_chunk, seed=k))
        if with_peers:
            out["reset_ms"] = [_reset_ms(lib, 20 * rounds)]
            out["traci_reset_ms"] = [_reset_ms(tra, 2 * rounds)]
    finally:
        lib.close()
        tra.close()
    return out


def speed(rounds: int, chunk: int, traci_chunk: int) -> dict[str, float]:
    """Medians of the per-round rates and ratios: one SUMO step per decision (``BENCH_CFG``),
    then the scenario's default decision interval."""
    rng = np.random.default_rng(0)
    one = _rounds(BENCH_CFG, rounds, chunk, traci_chunk, rng, with_peers=True)
    default = _rounds({"max_episode_steps": 100_000}, rounds, chunk, traci_chunk, rng, with_peers=False)
    med = statistics.median

    def ratio(a: list[float], b: list[float]) -> float:
        return med([x / y for x, y in zip(a, b)])

    return {
        "raw": med(one["raw"]),
        "env": med(one["env"]),
        "traci": med(one["traci"]),
        "getters": med(one["getters"]),
        "env_over_raw": ratio(one["env"], one["raw"]),
        "env_over_traci": ratio(one["env"], one["traci"]),
        "env_over_getters": ratio(one["env"], one["getters"]),
        "raw_over_traci": ratio(one["raw"], one["traci"]),
        "reset_ms": one["reset_ms"][0],
        "traci_reset_ms": one["traci_reset_ms"][0],
        "decision_interval": ScenarioConfig.ring().decision_interval,
        "default_raw": med(default["raw"]),
        "default_env": med(default["env"]),
        "default_traci": med(default["traci"]),
        "default_env_over_raw": ratio(default["env"], default["raw"]),
        "default_env_over_traci": ratio(default["env"], default["traci"]),
        "default_raw_over_traci": ratio(default["raw"], default["traci"]),
    }


COMMIT_CFG = {"commit_on_success": True}


def _commit_episode(env: LaneChangeEnv, seed: int) -> tuple[float, int] | None:
    """Seconds inside the committing ``step`` and the SUMO steps it simulated; None if the episode
    ended without a commit (the change collided, or no gap before the horizon)."""
    _obs, info = env.reset(seed=seed)
    while True:
        a = gap_acceptance_policy(info["points"])
        t0 = time.perf_counter()
        _obs, _r, term, trunc, info = env.step(a)
        dt = time.perf_counter() - t0
        if info["committed_steps"]:
            return (dt, (info["committed_steps"] + 1) * env.config.decision_interval) if info["event"] == "success" else None
        if term or trunc:
            return None


def _commit_raw(env: LaneChangeEnv, seed: int, sim_steps: int, getters: bool) -> float:
    """Seconds of raw libsumo stepping ``sim_steps`` from the seeded reset's state with the reward's reads."""
    env.reset(seed=seed)
    api = env.api
    vehicle = api.vehicle
    vehicle.unsubscribeContext(env.ego_id, env._tc.CMD_GET_VEHICLE_VARIABLE, env._ctx_range)  # no observation
    step, colliding = api.simulationStep, api.simulation.getCollidingVehiclesNumber
    speed_var = env._tc.VAR_SPEED
    di = env.config.decision_interval
    if getters:
        for vid in vehicle.getIDList():
            vehicle.unsubscribe(vid)
        get_ids, get_speed = vehicle.getIDList, vehicle.getSpeed
    t0 = time.perf_counter()
    for k in range(sim_steps):
        step()
        if colliding():
            pass
        if k % di == di - 1:
            if getters:
                ids = get_ids()
                _mean = math.fsum(map(get_speed, ids)) / len(ids)
            else:
                res = vehicle.getAllSubscriptionResults()
                _mean = math.fsum(r[speed_var] for r in res.values()) / len(res)
    return time.perf_counter() - t0


def commit_speed(rounds: int, episodes: int) -> dict[str, float | str]:
    """Medians over interleaved rounds: the commit step's simulated steps per second, raw libsumo's on
    the same seeds and lengths (the faster of its two ways to read the speeds), their ratio."""
    env = LaneChangeEnv(ScenarioConfig.ring(**COMMIT_CFG))
    envs, raws, ratios, wins, decisions = [], [], [], [], []
    try:
        seed = 0
        for _ in range(rounds):
            # each commit, then raw libsumo on the same seed and length right after it (a shared machine's
            # load drifts: the closer the pair, the better the ratio)
            env_s, steps, done = 0.0, 0, 0
            by_way = {"subscriptions": 0.0, "getters": 0.0}
            while done < episodes:
                got = _commit_episode(env, seed)
                if got is not None:
                    env_s += got[0]
                    steps += got[1]
                    done += 1
                    for way in by_way:
                        by_way[way] += _commit_raw(env, seed, got[1], way == "getters")
                seed += 1
            way, raw_s = min(by_way.items(), key=lambda kv: kv[1])
            envs.append(steps / env_s)
            raws.append(steps / raw_s)
            ratios.append(raw_s / env_s)
            wins.append(way)
            decisions.append(steps / env.config.decision_interval / done)
    finally:
        env.close()
    med = statistics.median
    return {
        "commit_env": med(envs),
        "commit_raw": med(raws),
        "commit_env_vs_raw": med(ratios),
        "commit_raw_reads": max(set(wins), key=wins.count),
        "commit_decisions": med(decisions),
        "commit_ratios": ratios,
    }


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


def exit_speed(rounds: int, chunk: int, resets: int) -> dict[str, float]:
    """The exit scenario (issue 44): env step (one SUMO step per decision, keep) against raw
    ``simulationStep`` on the same simulation and traffic, interleaved by rounds; and reset times
    (unseeded: traffic keeps running, the next ego is taken over; seeded: load + the warmed state)."""
    from sumo_bridge.lane_change_env import make_scenario_env

    env = make_scenario_env(scenario={"file": "exit", "decision_interval": 1, "max_episode_steps": 100_000})
    try:
        env.reset(seed=0)
        env_rates, raw_rates = [], []
        for _ in range(rounds):
            done, n, spent = False, 0, 0.0
            while n < chunk:
                if done:
                    env.reset()
                t0 = time.perf_counter()
                _o, _r, term, trunc, _i = env.step(0)
                spent += time.perf_counter() - t0
                n, done = n + 1, term or trunc
            env_rates.append(n / spent)
            step = env.api.simulationStep
            t0 = time.perf_counter()
            for _ in range(chunk):  # the same simulation: the env's subscriptions stay active, as in the ring row
                step()
            raw_rates.append(chunk / (time.perf_counter() - t0))
            env.reset()
        unseeded = []
        for _ in range(resets):
            t0 = time.perf_counter()
            env.reset()
            unseeded.append(1e3 * (time.perf_counter() - t0))
        seeded = []
        for k in range(max(3, resets // 10)):
            env.reset(seed=k % 3)  # warmed states cached after the first round
            t0 = time.perf_counter()
            env.reset(seed=k % 3)
            seeded.append(1e3 * (time.perf_counter() - t0))
        ratios = [e / r for e, r in zip(env_rates, raw_rates)]
        return {"exit_env_steps_per_s": statistics.median(env_rates), "exit_raw_steps_per_s": statistics.median(raw_rates),
                "exit_env_over_raw": statistics.median(ratios), "exit_vehicles": float(env.api.vehicle.getIDCount()),
                "exit_reset_ms_p50": statistics.median(unseeded), "exit_seeded_reset_ms_p50": statistics.median(seeded)}  # fmt: skip
    finally:
        env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps and episodes (a smoke run)")
    parser.add_argument("--no-policies", action="store_true", help="skip the scripted-policy success rates")
    parser.add_argument("--exit", action="store_true",
                        help="only the exit scenario: env step vs raw libsumo, and reset times (issue 44)")
    parser.add_argument("--commit-only", action="store_true", help="only the commit step against raw libsumo")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.exit:
        e = exit_speed(*((3, 300, 20) if args.quick else (9, 1500, 100)))
        for k, v in e.items():
            print(f"{k:<34}{v:>12.3f}")
        print(json.dumps({k: round(v, 3) for k, v in e.items()}))
        return 0
    rounds, chunk, traci_chunk, episodes = (3, 1000, 200, 30) if args.quick else (15, 2000, 400, 200)
    commit_rounds, commit_episodes = (3, 10) if args.quick else (9, 20)

    c = commit_speed(commit_rounds, commit_episodes)
    print(f"commit step (ring.yaml task, {c['commit_decisions']:.1f} decisions per committing step), simulated steps / s,"
          f" median of {commit_rounds} rounds of {commit_episodes} commits")
    print(f"{'env commit step':<34}{c['commit_env']:>12.0f}   {c['commit_env_vs_raw']:.3f} x raw"
          f" (rounds {', '.join(f'{r:.2f}' for r in c['commit_ratios'])})")
    print(f"{'raw libsumo, same reads':<34}{c['commit_raw']:>12.0f}   (speeds read by {c['commit_raw_reads']})")
    commit_json = {
        "commit_env_vs_raw": round(float(c["commit_env_vs_raw"]), 3),
        "commit_env_sim_steps_per_s": round(float(c["commit_env"]), 1),
        "commit_raw_sim_steps_per_s": round(float(c["commit_raw"]), 1),
        "commit_raw_reads": c["commit_raw_reads"],
        "commit_decisions_per_step": round(float(c["commit_decisions"]), 2),
    }
    if args.commit_only:
        print(json.dumps(commit_json))
        return 0

    m = speed(rounds, chunk, traci_chunk)
    print(f"{'measure (median of ' + str(rounds) + ' rounds)':<34}{'value':>12}")
    print(f"{'raw libsumo simulationStep / s':<34}{m['raw']:>12.0f}")
    print(f"{'env step / s (libsumo)':<34}{m['env']:>12.0f}   {m['env_over_raw']:.2f} x raw")
    print(f"{'env step / s (traci)':<34}{m['traci']:>12.0f}   libsumo env is {m['env_over_traci']:.1f} x")
    print(f"{'peer: traci with getters / s':<34}{m['getters']:>12.0f}   libsumo env is {m['env_over_getters']:.1f} x")
    print(f"{'ceiling: raw libsumo / traci env':<34}{m['raw_over_traci']:>12.2f}   (an env that only steps SUMO)")
    print(f"{'reset ms (libsumo / traci)':<34}{m['reset_ms']:>12.2f}   {m['traci_reset_ms']:.2f}")
    print(f"\ndefault decision_interval={m['decision_interval']}, simulated steps / s")
    print(f"{'env (libsumo)':<34}{m['default_env']:>12.0f}   {m['default_env_over_raw']:.2f} x raw ({m['default_raw']:.0f})")
    print(f"{'env (traci)':<34}{m['default_traci']:>12.0f}   libsumo env is {m['default_env_over_traci']:.1f} x"
          f" (ceiling {m['default_raw_over_traci']:.2f})")

    result: dict[str, object] = {
        **commit_json,
        "raw_steps_per_s": round(m["raw"], 1),
        "env_steps_per_s": round(m["env"], 1),
        "traci_env_steps_per_s": round(m["traci"], 1),
        "reset_ms": round(m["reset_ms"], 3),
        "env_over_raw": round(m["env_over_raw"], 3),
        "env_over_traci": round(m["env_over_traci"], 2),
        "traci_getters_steps_per_s": round(m["getters"], 1),
        "env_over_traci_getters": round(m["env_over_getters"], 2),
        "traci_reset_ms": round(m["traci_reset_ms"], 3),
        "raw_over_traci": round(m["raw_over_traci"], 2),
        "decision_interval_default": m["decision_interval"],
        "default_raw_steps_per_s": round(m["default_raw"], 1),
        "default_env_sim_steps_per_s": round(m["default_env"], 1),
        "default_traci_env_sim_steps_per_s": round(m["default_traci"], 1),
        "default_env_over_raw": round(m["default_env_over_raw"], 3),
        "default_env_over_traci": round(m["default_env_over_traci"], 2),
        "default_raw_over_traci": round(m["default_raw_over_traci"], 2),
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
