"""Success at what cost to others (issue 44): ``info["time_to_success"]`` and ``info["imposed_brake"]`` of
LaneChangeEnv -- a cut-in close in front of a follower imposes hard braking, a change into an empty lane none,
the fast-forward of a commit watches the follower as full decisions do, and SUMO's own lane changes are seen.

One libsumo simulation per process: every test closes its env before the next opens.
"""

from __future__ import annotations

from typing import Any

import pytest

from sumo_bridge.lane_change_env import BRAKE_WINDOW_SECONDS, LaneChangeEnv
from sumo_bridge.observation import SLOT_NAMES, field_index
from sumo_bridge.scenario import ScenarioConfig
from sumo_bridge.scenario_file import scenario_from_kwargs

GAP, PRESENT, REL, SPEED = field_index("gap"), field_index("present"), field_index("rel_speed"), field_index("speed")
ROW = {name: 1 + i for i, name in enumerate(SLOT_NAMES)}


def _cut_in_moment(env: LaneChangeEnv, seeds: range) -> tuple[int, int]:
    """(seed, keeps): the first moment of the keep policy at which the target lane's follower is less than
    1.5 m behind the ego and at most 2 m/s slower (it must brake for the ego), the leader clear ahead."""
    for seed in seeds:
        _obs, info = env.reset(seed=seed)
        for keeps in range(env.config.max_episode_steps - 10):
            f, lead = info["points"][ROW["left_follower"]], info["points"][ROW["left_leader"]]
            if (f[PRESENT] > 0.5 and f[GAP] < 1.5 and f[REL] > -2.0
                    and (lead[PRESENT] < 0.5 or (lead[GAP] > 3.0 and lead[REL] > -1.0))):  # fmt: skip
                return seed, keeps
            _obs, _r, terminated, truncated, info = env.step(0)
            assert not (terminated or truncated)
    raise AssertionError(f"no cut-in moment in seeds {seeds}")


def _cut_in_episode(env: LaneChangeEnv, seed: int, keeps: int) -> tuple[dict[str, Any], str, list[float]]:
    """Keep ``keeps`` decisions, change left, keep to the end. Returns the last info, the follower cut in on,
    and its speed at the end of every decision from the change until the window closes."""
    _obs, info = env.reset(seed=seed)
    for _ in range(keeps):
        _obs, _r, _term, _trunc, info = env.step(0)
    follower = env.neighbour_ids()["left_follower"]
    assert follower is not None
    _obs, _r, terminated, truncated, info = env.step(1)
    speeds = [env.api.vehicle.getSpeed(follower)]
    window = round(BRAKE_WINDOW_SECONDS / env.step_seconds)
    while not (terminated or truncated):
        _obs, _r, terminated, truncated, info = env.step(0)
        if len(speeds) <= window:
            speeds.append(env.api.vehicle.getSpeed(follower))
    return info, follower, speeds


def test_a_cut_in_close_in_front_of_a_follower_imposes_hard_braking() -> None:
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        seed, keeps = _cut_in_moment(env, range(20, 40))
        info, follower, speeds = _cut_in_episode(env, seed, keeps)
        assert info["event"] == "success" and info["lane_changes_done"] == 1
        brake = info["imposed_brake"]
        # MOBIL's b_safe is ~4 m/s²: a cut-in at < 1.5 m makes the follower brake beyond it, within its limit
        assert 4.0 < brake <= env.api.vehicle.getEmergencyDecel(follower) + 1e-9, brake
        # the watched vehicle is the follower cut in on: its mean deceleration over each watched decision is
        # at most the strongest single step's (read independently, by speed, at the decisions' ends)
        drops = [(a - b) / env.step_seconds for a, b in zip(speeds, speeds[1:])]
        assert max(drops) <= brake + 1e-9 and max(drops) > 1.0, drops
    finally:
        env.close()


def _empty_target_lane(env: LaneChangeEnv, seed: int) -> dict[str, Any]:
    """A reset, then every vehicle on the target lane removed and the others held on their lanes."""
    _obs, info = env.reset(seed=seed)
    vehicle = env.api.vehicle
    for vid in vehicle.getIDList():
        if vid == env.ego_id:
            continue
        if vehicle.getLaneIndex(vid) == env.config.target:
            vehicle.unsubscribe(vid)  # the env's speed subscription (SUMO would evaluate it for a vehicle gone)
            vehicle.remove(vid)
        else:
            vehicle.setLaneChangeMode(vid, 0)
    _obs, _r, _term, _trunc, info = env.step(0)
    assert not any(vehicle.getLaneIndex(v) == env.config.target for v in vehicle.getIDList() if v != env.ego_id)
    return info


def test_a_change_into_an_empty_lane_imposes_nothing_and_time_to_success_counts_decisions() -> None:
    """Into an empty lane nobody brakes: 0.0 exactly. The time to success is decisions x decision_interval x
    step_length, also when the commit runs the rest of the horizon inside the successful transition."""
    for commit in (False, True):
        env = LaneChangeEnv(ScenarioConfig.ring(commit_on_success=commit))
        try:
            info = _empty_target_lane(env, seed=21)
            assert info["time_to_success"] is None and info["imposed_brake"] == 0.0
            _obs, _r, terminated, truncated, info = env.step(1)
            assert info["target_reached"] and info["lane_changes_done"] == 1
            assert env.api.vehicle.getFollower(env.ego_id)[0] == ""  # nobody behind on the new lane
            decisions = 2  # one keep, the change
            assert info["episode_step"] == (env.config.max_episode_steps if commit else decisions)
            while not (terminated or truncated):
                _obs, _r, terminated, truncated, info = env.step(0)
            cfg = env.config
            assert info["event"] == "success" and info["imposed_brake"] == 0.0
            assert info["time_to_success"] == pytest.approx(decisions * cfg.decision_interval * cfg.step_length)
            assert info["sim_time"] == pytest.approx(cfg.max_episode_steps * cfg.decision_interval * cfg.step_length)
            assert info["committed_steps"] == (cfg.max_episode_steps - decisions if commit else 0)
        finally:
            env.close()


def test_keeping_the_lane_imposes_nothing_and_never_succeeds() -> None:
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        env.reset(seed=22)
        terminated = truncated = False
        while not (terminated or truncated):
            _obs, _r, terminated, truncated, info = env.step(0)
        assert info["event"] == "time_limit" and info["time_to_success"] is None
        assert info["imposed_brake"] == 0.0 and info["lane_changes_done"] == 0
    finally:
        env.close()


def test_the_commit_fast_forward_watches_the_follower_as_full_decisions_do(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cut-in's window runs on into the commit's fast-forward (context and speed subscriptions dropped):
    the same episode on the fixed horizon (full decisions, the same SUMO steps) reads the same follower at the
    same steps and gets the same values, one reading per SUMO step of the window."""
    out = []
    for commit in (False, True):
        env = LaneChangeEnv(ScenarioConfig.ring(commit_on_success=commit))
        try:
            if not out:
                seed, keeps = _cut_in_moment(env, range(20, 40))
            readings: list[tuple[int, str, float]] = []
            get = env.api.vehicle.getAcceleration

            def recorded(vid: str, env: LaneChangeEnv = env, get: Any = get,
                         readings: list[tuple[int, str, float]] = readings) -> float:  # fmt: skip
                value = get(vid)
                if env._tracking:  # the watch's readings (the ring's reset reads accelerations too)
                    readings.append((env._substep, vid, value))
                return value

            monkeypatch.setattr(env.api.vehicle, "getAcceleration", recorded)
            info, follower, _speeds = _cut_in_episode(env, seed, keeps)
            monkeypatch.undo()
            out.append((info["event"], info["imposed_brake"], info["time_to_success"], info["committed_steps"],
                        follower, readings))  # fmt: skip
        finally:
            env.close()
    (event_f, brake_f, tts_f, committed_f, follower, readings_f), (event_c, brake_c, tts_c, committed_c, _, readings_c) = out
    assert event_f == event_c == "success" and committed_f == 0 and committed_c > 0
    assert brake_f > 4.0 and brake_c == brake_f and tts_c == tts_f
    window = round(BRAKE_WINDOW_SECONDS / ScenarioConfig.ring().step_length)
    change = keeps * ScenarioConfig.ring().decision_interval  # the SUMO step that carries the change out
    assert readings_c == readings_f and [k for k, _, _ in readings_c] == list(range(change + 1, change + 1 + window))
    assert {vid for _, vid, _ in readings_c} == {follower}
    assert max(-a for _, _, a in readings_c) == brake_c
    fast = [r for r in readings_c if r[0] >= change + ScenarioConfig.ring().decision_interval]  # in the fast-forward
    assert len(fast) == window - ScenarioConfig.ring().decision_interval + 1


def test_sumos_own_lane_changes_are_watched_on_the_exit() -> None:
    """The 'sumo' baseline on the exit: SUMO's model (laneChangeMode 1621) crosses the three lanes by itself,
    no command given; each change is seen and its new follower watched."""
    cfg = scenario_from_kwargs("scenario", {"file": "exit", "ego_lane_change_mode": 1621})
    env = LaneChangeEnv(cfg)
    try:
        env.reset(seed=1_500_000_001)
        terminated = truncated = False
        while not (terminated or truncated):
            _obs, _r, terminated, truncated, info = env.step(0)
        assert info["event"] == "success" and info["lane_changes"] == 0  # nothing commanded
        assert info["lane_changes_done"] >= 3  # leftmost of four lanes to the ramp's
        assert info["time_to_success"] == pytest.approx(info["episode_step"] * cfg.decision_interval * cfg.step_length)
        assert info["imposed_brake"] > 0.0
    finally:
        env.close()
