"""Evaluation episodes of a policy on several environments stepped in lockstep.

An evaluation runs ``n`` episodes: ``ceil(n / episodes_per_seed)`` seeded resets, each followed by
``episodes_per_seed - 1`` unseeded ones (the urban network keeps its traffic running between
episodes and a seeded reset costs a 150 s warm-up, so it evaluates in streams of episodes; the
ring and gymnasium's envs use one seed per episode). The result of an evaluation depends only on
the network's weights and the seeds, not on when or in which process it runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from der_ros.train.eval_policies import Policy
from der_ros.train.eval_result import OUTCOMES, EpisodeResult

__all__ = ["run_episodes"]


def _outcome(info: dict[str, Any], terminated: bool, truncated: bool) -> tuple[str, bool]:
    event = info.get("event")
    if event in OUTCOMES:
        return str(event), bool(info.get("caused", False))
    return ("terminated" if terminated else "time_limit"), False


def _episode_over(env: Any, info: dict[str, Any], terminated: bool, truncated: bool) -> bool:
    """Atari with episodic life: only a game over ends an evaluation episode."""
    if not (terminated or truncated):
        return False
    if "episode" in info or getattr(env.unwrapped, "ale", None) is None:
        return True
    return bool(truncated) or bool(env.unwrapped.ale.game_over())


def run_episodes(
    policy: Policy,
    envs: Sequence[Any],
    seeds: Sequence[int],
    episodes: int,
    episodes_per_seed: int = 1,
) -> list[EpisodeResult]:
    """Run ``episodes`` evaluation episodes of ``policy`` on ``envs`` (stepped in lockstep).

    Stream ``j`` (seed ``seeds[j]``) is a seeded reset followed by ``episodes_per_seed - 1``
    unseeded ones; streams are dealt to the environments in order, so the result does not depend
    on how many environments there are. Results come back in stream order.
    """
    if episodes_per_seed < 1:
        raise ValueError(f"episodes_per_seed = {episodes_per_seed}, expected >= 1")
    n_streams = math.ceil(episodes / episodes_per_seed) if episodes else 0
    if len(seeds) < n_streams:
        raise ValueError(f"{episodes} episodes in streams of {episodes_per_seed} need {n_streams} seeds, got {len(seeds)}")
    sizes = [min(episodes_per_seed, episodes - j * episodes_per_seed) for j in range(n_streams)]
    results: dict[tuple[int, int], EpisodeResult] = {}
    next_stream = 0
    # per env: [stream, episode index in stream, obs, info, return, length] or None when idle
    slots: list[list[Any] | None] = [None] * len(envs)

    def start(i: int, stream: int, k: int) -> None:
        env = envs[i]
        obs, info = env.reset(seed=int(seeds[stream])) if k == 0 else env.reset()
        slots[i] = [stream, k, obs, info, 0.0, 0]

    for i in range(len(envs)):
        if next_stream < n_streams:
            start(i, next_stream, 0)
            next_stream += 1
    while any(s is not None for s in slots):
        active = [i for i, s in enumerate(slots) if s is not None]
        obs = np.stack([slots[i][2] for i in active])  # type: ignore[index]
        actions = policy(obs, [slots[i][3] for i in active])  # type: ignore[index]
        for i, a in zip(active, actions):
            slot = slots[i]
            assert slot is not None
            env = envs[i]
            o, r, terminated, truncated, info = env.step(int(a))
            slot[2], slot[3] = o, info
            slot[4] += float(r)
            slot[5] += 1
            if terminated or truncated:
                if not _episode_over(env, info, terminated, truncated):
                    slot[2], _ = env.reset()  # Atari life lost: the game goes on
                    continue
                stream, k = slot[0], slot[1]
                ret = float(np.asarray(info["episode"]["r"])) if "episode" in info else slot[4]
                outcome, caused = _outcome(info, terminated, truncated)
                tts, brake = info.get("time_to_success"), info.get("imposed_brake")
                results[(stream, k)] = EpisodeResult(
                    seed=int(seeds[stream]) if k == 0 else None, stream=stream, ret=ret, length=int(slot[5]),
                    outcome=outcome, caused=caused, interventions=int(info.get("interventions", 0)),
                    time_to_success=float(tts) if outcome == "success" and tts is not None else None,
                    imposed_brake=None if brake is None else float(brake),
                )  # fmt: skip
                if k + 1 < sizes[stream]:
                    start(i, stream, k + 1)
                elif next_stream < n_streams:
                    start(i, next_stream, 0)
                    next_stream += 1
                else:
                    slots[i] = None
    return [results[key] for key in sorted(results)]
