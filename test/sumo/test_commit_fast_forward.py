"""The commit fast-forward (``LaneChangeEnv._commit_rest``) gives the full decisions' episodes bit for bit.

The reference is the path the fast-forward replaced, kept here only: after a change commits, the rest
of the horizon as repeated full decisions (``_ReferenceEnv._advance_full(0)``: the context subscription
evaluated and read, the observation rebuilt, at every decision). Both envs run the same action streams
(seeded resets, then unseeded resets that carry the simulation over, so the SUMO state after a commit
is compared too), one after the other (one libsumo simulation per process). Compared per step: the
observation's bytes, the reward's bits, terminated / truncated, and every info field (points bytes).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig


class _ReferenceEnv(LaneChangeEnv):
    """``LaneChangeEnv`` with the commit as it ran before the fast-forward (full decisions)."""

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("step() called after the episode ended; call reset()")
        reward, terminated, truncated, event, caused, mean_speed, ego_gone = self._advance_full(int(action))
        if self._commit and self._target_reached and not (terminated or truncated):
            committed = 0
            while not (terminated or truncated):
                r, terminated, truncated, event, caused, mean_speed, ego_gone = self._advance_full(0)
                reward += r
                committed += 1
            terminated, truncated = True, False
            self._committed_steps = committed
        self._done = terminated or truncated
        if ego_gone:
            self._ego_present = False
        info = self._info(event=event, mean_speed=mean_speed)
        info["caused"] = caused
        info["committed_steps"] = self._committed_steps
        obs = self._obs.copy() if ego_gone else self._obs
        return obs, float(reward), terminated, truncated, info

    def _advance_full(self, a: int) -> tuple[float, bool, bool, str | None, bool, float, bool]:
        """The decision as written before the fast-forward existed (one function, nothing shared)."""
        cfg, api = self.config, self.api
        if a != 0 and not (self._target_reached and self._hold_target):
            new_lane = self._ego_lane + 1 if a == 1 else self._ego_lane - 1
            if 0 <= new_lane < self._ego_lane_count:
                api.vehicle.changeLane(self.ego_id, new_lane, self.step_seconds)
                self._last_change_substep = self._substep
                self._lane_changes += 1
        collided = False
        for _ in range(cfg.decision_interval):
            self._sim_step()
            self._substep += 1
            if self._colliding:
                for c in api.simulation.getCollisions():
                    if self.ego_id in (c.collider, c.victim):
                        collided = True
                        break
                if collided:
                    break
        self._episode_step += 1
        ctx = api.vehicle.getContextSubscriptionResults(self.ego_id)
        ego_gone = not ctx or self.ego_id not in ctx
        if not ego_gone:
            self._points_from_context(ctx)
        mean_speed = self._mean_speed()
        reward = math.log(max(mean_speed, cfg.min_speed))
        terminated = truncated = False
        event: str | None = None
        caused = False
        if collided:
            terminated, event = True, "collision"
            caused = self._last_change_substep is not None and (
                (self._substep - self._last_change_substep) * cfg.step_length <= cfg.collision_window + 1e-9
            )
            if caused:
                reward += cfg.reward_collision
        elif self._target_reached:
            pass
        elif not ego_gone and self._ego_lane == cfg.target:
            if self._on_target_since is None:
                changed_now = self._last_change_substep is not None and self._last_change_substep >= self._substep - cfg.decision_interval
                self._on_target_since = self._last_change_substep + 1 if changed_now else self._substep
            if (self._substep - self._on_target_since) * cfg.step_length >= cfg.settle_time - 1e-9:
                self._target_reached = True
                reward += cfg.reward_success
                if cfg.success_ends_episode:
                    terminated, event = True, "success"
        else:
            self._on_target_since = None
        if not terminated and (ego_gone or self._episode_step >= cfg.max_episode_steps):
            truncated, event = True, ("success" if self._target_reached else "time_limit")
        return reward, terminated, truncated, event, caused, mean_speed, ego_gone


def _key(x: Any) -> Any:
    """A comparable, bit-exact form of a step's output (arrays as dtype + shape + bytes, floats as hex)."""
    if isinstance(x, np.ndarray):
        return ("array", str(x.dtype), x.shape, x.tobytes())
    if isinstance(x, float):
        return ("float", x.hex())
    if isinstance(x, dict):
        return {k: _key(v) for k, v in x.items()}
    if isinstance(x, (tuple, list)):
        return type(x)(_key(v) for v in x)
    return x


def _episodes(env: LaneChangeEnv, seeds: range, episodes_per_seed: int) -> list[Any]:
    """Every step of ``episodes_per_seed`` episodes per seed (a seeded reset, then unseeded ones) under a
    seeded policy that keeps mostly and changes lanes often enough to commit, and to collide."""
    out: list[Any] = []
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        for ep in range(episodes_per_seed):
            obs, info = env.reset(seed=seed) if ep == 0 else env.reset()
            out.append(_key(("reset", obs, info)))
            done = False
            while not done:
                u = rng.random()
                action = 1 if u < 0.25 else (2 if u < 0.30 else 0)
                obs, reward, terminated, truncated, info = env.step(action)
                out.append(_key((action, obs, reward, terminated, truncated, info)))
                done = terminated or truncated
    return out


def _run(cls: type[LaneChangeEnv], cfg: ScenarioConfig, seeds: range, episodes: int, fast_cap: int | None = None,
         monkeypatch: pytest.MonkeyPatch | None = None) -> list[Any]:  # fmt: skip
    env = cls(cfg)
    try:
        if fast_cap is not None and monkeypatch is not None:  # the bound allows fast_cap decisions, then none
            bound, step = LaneChangeEnv._commit_fast_decisions, env.step
            calls = [0]

            def counted_step(action: Any) -> Any:
                calls[0] = 0
                return step(action)

            def capped() -> int:
                calls[0] += 1
                return min(fast_cap, bound(env)) if calls[0] == 1 else 0

            monkeypatch.setattr(env, "step", counted_step)
            monkeypatch.setattr(env, "_commit_fast_decisions", capped)
        return _episodes(env, seeds, episodes)
    finally:
        env.close()


def _commit_summary(steps: list[Any]) -> tuple[int, int]:
    """(commits, commits that ended in a collision) among the recorded steps."""
    commits = [s for s in steps if s[0] != "reset" and s[-1]["committed_steps"] > 0]
    return len(commits), sum(1 for s in commits if s[-1]["event"] == "collision")


def _assert_same(ref: list[Any], new: list[Any]) -> None:
    assert len(new) == len(ref)
    for i, (a, b) in enumerate(zip(ref, new)):
        assert a == b, f"step {i} differs"


@pytest.mark.slow
def test_ring_commit_fast_forward_is_bit_identical() -> None:
    cfg = ScenarioConfig.ring(commit_on_success=True)
    seeds, episodes = range(40), 4
    ref = _run(_ReferenceEnv, cfg, seeds, episodes)
    new = _run(LaneChangeEnv, cfg, seeds, episodes)
    commits, collisions = _commit_summary(ref)
    assert commits >= 60, commits
    _assert_same(ref, new)


def test_ring_commit_ending_in_a_collision_and_switching_midway_are_bit_identical(monkeypatch: pytest.MonkeyPatch) -> None:
    """A commit that ends in a collision (settle_time 0.1 s: the success is paid a step after the change,
    so a change into a short gap collides inside the commit; seed 43's 4th episode does), and the
    path taken when the ego could leave the network before the horizon (a cap on the fast decisions):
    some fast decisions, then the context subscription back and the rest in full."""
    cfg = ScenarioConfig.ring(commit_on_success=True, settle_time=0.1)
    seeds, episodes = range(40, 45), 4
    ref = _run(_ReferenceEnv, cfg, seeds, episodes)
    commits, collisions = _commit_summary(ref)
    assert commits >= 8 and collisions >= 1, (commits, collisions)
    for cap in (None, 0, 3):
        _assert_same(ref, _run(LaneChangeEnv, cfg, seeds, episodes, fast_cap=cap, monkeypatch=monkeypatch))


@pytest.mark.slow
def test_urban_commit_fast_forward_is_bit_identical() -> None:
    cfg = ScenarioConfig.urban(commit_on_success=True)
    seeds, episodes = range(4), 5
    ref = _run(_ReferenceEnv, cfg, seeds, episodes)
    new = _run(LaneChangeEnv, cfg, seeds, episodes)
    commits, _collisions = _commit_summary(ref)
    assert commits >= 5, commits
    _assert_same(ref, new)


def test_fast_decisions_cover_the_ring_horizon() -> None:
    """On the ring (routes of several laps) every decision after a commit runs fast."""
    env = LaneChangeEnv(ScenarioConfig.ring(commit_on_success=True))
    try:
        env.reset(seed=3)
        assert env._commit_fast_decisions() == env.config.max_episode_steps - env._episode_step
    finally:
        env.close()
