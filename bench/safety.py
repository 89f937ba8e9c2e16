"""Benchmark: the safety shield's cost per decision, in one process (docs/safety.md).

On points of real ring states (the first ``--states`` states of evaluation episodes, the
change-now driver behind the shield so the target lane is often occupied), per decision:

* ``rss_mask_us`` -- :meth:`RssChecker.mask` (both sides, both slots: what the wrapper and the
  safety node run per step);
* ``filter_decide_us`` -- :class:`CommandFilter` state + decide (the safety node's core);
* ``obs_mask_batch128_us`` -- :class:`ObservationMask` of a batch of 128 (mask mode's target);
* peers in the same process: ``greedy_forward_us`` (the agent's one-observation Q-network forward,
  what a decision costs the agent), ``env_step_us`` (one ring env step), ``ad_rss_us`` (Intel's
  ad-rss: the two distances of one side, states prebuilt, where installed).

Ends with one JSON line (medians of ``--repeats`` timed loops).

    .venv/bin/python bench/safety.py [--states 500] [--repeats 7]
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from der_ros.configuration import from_dict  # noqa: E402
from der_ros.safety.checker import RssChecker  # noqa: E402
from der_ros.safety.command_filter import CommandFilter  # noqa: E402
from der_ros.safety.config import SafetyConfig  # noqa: E402
from der_ros.safety.observation_mask import ObservationMask  # noqa: E402
from der_ros.train.config import EnvConfig  # noqa: E402
from der_ros.train.envs import make_env_from_config  # noqa: E402
from sumo_bridge.observation import ObservationConfig, encode_observation  # noqa: E402
from sumo_bridge.policies import immediate_policy  # noqa: E402


def timed(fn, n: int, repeats: int) -> float:  # noqa: ANN001
    """Median µs per call of ``fn(i)`` over ``repeats`` loops of ``n`` calls."""
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        runs.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(runs)


def collect_states(n: int) -> tuple[list[np.ndarray], float]:
    env = make_env_from_config(from_dict(EnvConfig, {"id": "der_ros/LaneChangeRing-v0", "safety": {"kind": "rss"}}), 0)
    states, step_s, steps = [], 0.0, 0
    seed = 1_000_000_000
    try:
        _, info = env.reset(seed=seed)
        while len(states) < n:
            states.append(info["points"].copy())
            t0 = time.perf_counter()
            _, _, term, trunc, info = env.step(immediate_policy(info["points"]))
            step_s += time.perf_counter() - t0
            steps += 1
            if term or trunc:
                seed += 1
                _, info = env.reset(seed=seed)
    finally:
        env.close()
    return states, step_s / steps * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    states, env_step_us = collect_states(args.states)
    n = len(states)
    cfg = SafetyConfig(kind="rss")
    checker = RssChecker(cfg)
    rss_us = timed(lambda i: checker.mask(states[i]), n, args.repeats)
    filt = CommandFilter(checker.mask)
    stamps = itertools.count(1)  # ever newer stamps: every command is judged on its state (never stale)

    def decide(i: int) -> None:
        k = next(stamps)
        filt.on_state(k, states[i], 0.0)
        filt.decide(k, 1, 0.0)

    filter_us = timed(decide, n, args.repeats)
    assert filt.counters["stale"] == 0 and filt.counters["no_state"] == 0, filt.counters
    obs_cfg = ObservationConfig()
    obs = np.stack([encode_observation(p, obs_cfg) for p in states])
    batch = obs[:128]
    om = ObservationMask(cfg, obs_cfg)
    obs_mask_us = timed(lambda i: om(batch), 200, args.repeats)

    import torch

    from der_ros.agent.networks import make_q_network

    torch.set_num_threads(1)
    net = make_q_network(obs.shape[1:], np.float32, 3, "mlp", [256])
    with torch.inference_mode():
        forward_us = timed(lambda i: net(torch.from_numpy(obs[i : i + 1])).argmax(1).item(), n, args.repeats)
    result = {"bench": "safety", "states": n, "rss_mask_us": round(rss_us, 2), "filter_decide_us": round(filter_us, 2),
              "obs_mask_batch128_us": round(obs_mask_us, 1), "greedy_forward_us": round(forward_us, 1),
              "env_step_us": round(env_step_us, 1),
              "rss_mask_vs_forward": round(rss_us / forward_us, 3), "rss_mask_vs_env_step": round(rss_us / env_step_us, 4)}
    try:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
        from ad_rss import physics, rss
        from test_safety_rss import _state  # the fully-filled ad-rss states (its pitfalls: test/test_safety_rss.py)

        pairs = [(_state(float(p[0][3]) + 1.0, 0.5, 2.6, 4.5, 9.0), _state(float(p[0][3]), 0.5, 2.6, 4.5, 9.0))
                 for p in states[:100]]  # fmt: skip
        out = physics.Distance(0.0)
        f = rss.structured.calculateSafeLongitudinalDistanceSameDirection

        def two(i: int) -> None:
            a, b = pairs[i % len(pairs)]
            f(a, b, out)
            f(b, a, out)

        result["ad_rss_two_distances_us"] = round(timed(two, len(pairs), args.repeats), 2)
    except ImportError:
        result["ad_rss_two_distances_us"] = None
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
