"""Benchmark: how varied the ring's episode starts are with warm-state re-placements (not a test).

Unseeded ring resets rebuild the traffic only every ``ring_rebuild_every`` episodes and put the
last build's traffic back in between (``sumo_bridge/warm_state.py``). This script measures what
that does to the task, on the ring scenario of ``config/ring.yaml``:

1. The first observation of an episode: speed and gap of every occupied neighbour slot (and
   the ego's speed), for ``--episodes`` seeded resets (every one a full build: the reference,
   as every reset was before), for the same number of unseeded resets of a training-like stream
   (the configured ``ring_rebuild_every``), and for the stream with ``ring_rebuild_every = 1``
   (every reset a build; how far two samples of the reference law lie apart by chance).
   Printed: presence rates, 10/50/90 % quantiles, two-sample Kolmogorov-Smirnov statistics
   against the reference. The stream's episodes are driven by a fixed policy (keep the lane,
   a random action with probability 0.1).
2. Scripted policies (``sumo_bridge.policies``) over ``--policy-episodes`` stream episodes,
   with and without re-placements: outcome rates, mean return, background lane changes per episode.
3. Reset times of the stream: p50 of re-placements and of builds.

    .venv/bin/python bench/reset_variety.py            # 500 episodes, 300 per policy (~5 min)
    .venv/bin/python bench/reset_variety.py --quick    # 100 episodes, 50 per policy

Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.train.config import load_experiment_config
from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.observation import SLOT_NAMES, field_index
from sumo_bridge.policies import gap_acceptance_policy, keep_policy
from sumo_bridge.scenario import ScenarioConfig, scenario_from_kwargs

RING_YAML = Path(__file__).resolve().parent.parent / "config" / "ring.yaml"
SPEED, GAP, PRESENT = field_index("speed"), field_index("gap"), field_index("present")
ROWS = {"ego": 0, **{name: 1 + i for i, name in enumerate(SLOT_NAMES[:4])}}  # the ring has no right lane


def ks_statistic(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov statistic: the largest gap between the two empirical CDFs."""
    a, b = np.sort(a), np.sort(b)
    grid = np.concatenate([a, b])
    return float(
        np.max(np.abs(np.searchsorted(a, grid, "right") / a.size - np.searchsorted(b, grid, "right") / b.size))
    )


def ring_scenario(**overrides: Any) -> ScenarioConfig:
    cfg = load_experiment_config(RING_YAML, {})
    return dataclasses.replace(scenario_from_kwargs("ring", cfg.env.kwargs.get("scenario")), **overrides)


def _run_episode(
    env: LaneChangeEnv, info: dict[str, Any], policy: Callable[[np.ndarray], int]
) -> tuple[str, float, int]:
    """(event, return, background lane changes) of one episode."""
    v = env.api.vehicle
    lanes = {vid: v.getLaneIndex(vid) for vid in v.getIDList() if vid != env.ego_id}
    total, changes, done = 0.0, 0, False
    while not done:
        _obs, r, terminated, truncated, info = env.step(policy(info["points"]))
        total += r
        done = terminated or truncated
        for vid, lane in lanes.items():
            now = v.getLaneIndex(vid)
            if now != lane:
                changes += 1
                lanes[vid] = now
    return str(info["event"]), total, changes


def seeded_starts(scenario: ScenarioConfig, n: int, base: int) -> np.ndarray:
    env = LaneChangeEnv(scenario)
    try:
        return np.array([env.reset(seed=base + k)[1]["points"] for k in range(n)])
    finally:
        env.close()


def stream_starts(scenario: ScenarioConfig, n: int, seed: int) -> tuple[np.ndarray, list[float], list[float]]:
    """First points of ``n`` episodes of an unseeded stream; reset times of re-placements and builds."""
    env = LaneChangeEnv(scenario)
    rng = np.random.default_rng(seed)

    def policy(_points: np.ndarray) -> int:
        return int(rng.integers(3)) if rng.random() < 0.1 else 0

    replays: list[float] = []
    builds: list[float] = []
    try:
        _obs, info = env.reset(seed=seed)
        starts = [info["points"]]
        for _ in range(n - 1):
            _run_episode(env, info, policy)
            t = time.perf_counter()
            _obs, info = env.reset()
            (builds if env._episodes_since_load == 1 else replays).append(time.perf_counter() - t)
            starts.append(info["points"])
        return np.array(starts), replays, builds
    finally:
        env.close()


def policy_outcomes(scenario: ScenarioConfig, n: int, seed: int) -> dict[str, dict[str, float]]:
    env = LaneChangeEnv(scenario)
    out = {}
    try:
        for name, policy in (("gap_acceptance", gap_acceptance_policy), ("keep", keep_policy)):
            _obs, info = env.reset(seed=seed)
            rows = []
            for _ in range(n):
                rows.append(_run_episode(env, info, policy))
                _obs, info = env.reset()
            events = np.array([r[0] for r in rows])
            out[name] = {
                "success": float(np.mean(events == "success")),
                "collision": float(np.mean(events == "collision")),
                "mean_return": float(np.mean([r[1] for r in rows])),
                "sd_return": float(np.std([r[1] for r in rows])),
                "bg_lane_changes": float(np.mean([r[2] for r in rows])),
            }
    finally:
        env.close()
    return out


def compare(ref: np.ndarray, other: np.ndarray) -> dict[str, dict[str, float]]:
    table = {}
    for name, row in ROWS.items():
        a, b = ref[:, row], other[:, row]
        pa, pb = a[:, PRESENT] > 0.5, b[:, PRESENT] > 0.5
        entry = {"present_ref": float(pa.mean()), "present": float(pb.mean())}
        for field, col in (("speed", SPEED), ("gap", GAP)):
            if name == "ego" and field == "gap":
                continue
            x, y = a[pa, col], b[pb, col]
            entry[f"{field}_q_ref"] = [round(float(q), 2) for q in np.percentile(x, [10, 50, 90])]
            entry[f"{field}_q"] = [round(float(q), 2) for q in np.percentile(y, [10, 50, 90])]
            entry[f"{field}_ks"] = round(ks_statistic(x, y), 3)
        table[name] = entry
    return table


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100 episodes, 50 per policy")
    parser.add_argument("--episodes", type=int, default=None, help="episode starts per sample (default 500)")
    parser.add_argument("--policy-episodes", type=int, default=None, help="episodes per scripted policy (default 300)")
    parser.add_argument("--no-policies", action="store_true", help="skip the scripted policies")
    parser.add_argument("--rebuild-every", type=int, default=None, help="ring_rebuild_every (default: ring.yaml's)")
    args = parser.parse_args()
    n = args.episodes or (100 if args.quick else 500)
    n_policy = args.policy_episodes or (50 if args.quick else 300)
    scenario = ring_scenario()
    if args.rebuild_every is not None:
        scenario = dataclasses.replace(scenario, ring_rebuild_every=args.rebuild_every)
    every = scenario.ring_rebuild_every

    reference = seeded_starts(dataclasses.replace(scenario, ring_rebuild_every=1), n, base=10_000)
    stream, replays, builds = stream_starts(scenario, n, seed=20_000)
    stream1, _, builds1 = stream_starts(dataclasses.replace(scenario, ring_rebuild_every=1), n, seed=20_000)
    vs_stream = compare(reference, stream)
    vs_stream1 = compare(reference, stream1)
    print(f"first observation of {n} episodes: seeded builds (reference) vs the unseeded stream with "
          f"ring_rebuild_every = {every} [and = 1, the chance level]", file=sys.stderr)  # fmt: skip
    for name in ROWS:
        e, e1 = vs_stream[name], vs_stream1[name]
        line = f"  {name:14s} present {e['present_ref']:.2f} / {e['present']:.2f}"
        for field in ("speed", "gap"):
            if f"{field}_ks" in e:
                line += (f" | {field} q10/50/90 {e[f'{field}_q_ref']} / {e[f'{field}_q']} "
                         f"KS {e[f'{field}_ks']:.3f} [{e1[f'{field}_ks']:.3f}]")  # fmt: skip
        print(line, file=sys.stderr)
    policies = {}
    if not args.no_policies:
        policies[f"rebuild_every_{every}"] = policy_outcomes(scenario, n_policy, seed=777)
        policies["rebuild_every_1"] = policy_outcomes(
            dataclasses.replace(scenario, ring_rebuild_every=1), n_policy, seed=777
        )
    for label, table in policies.items():
        for name, row in table.items():
            print(f"  {label:18s} {name:15s} " + "  ".join(f"{k} {v:.3f}" for k, v in row.items()), file=sys.stderr)
    result = {
        "bench": "reset_variety",
        "episodes": n,
        "policy_episodes": n_policy,
        "ring_rebuild_every": every,
        "ks_vs_seeded": {name: {k: v for k, v in e.items() if k.endswith("_ks")} for name, e in vs_stream.items()},
        "ks_chance_level": {name: {k: v for k, v in e.items() if k.endswith("_ks")} for name, e in vs_stream1.items()},
        "first_observation": vs_stream,
        "policies": policies,
        "replay_ms_p50": round(1e3 * float(np.median(replays)), 3),
        "build_ms_p50": round(1e3 * float(np.median(builds + builds1)), 3),
        "reset_ms_p50": round(1e3 * float(np.median(replays + builds)), 3),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
