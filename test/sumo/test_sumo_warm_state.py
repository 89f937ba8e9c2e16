"""Ring resets: full builds on seeded resets and every ``ring_rebuild_every`` episodes, warm-state
re-placements in between (sumo_bridge.warm_state). One libsumo simulation per process: every test
closes its env before the next opens one."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.observation import field_index
from sumo_bridge.policies import immediate_policy, keep_policy
from sumo_bridge.scenario import ScenarioConfig

LANE = field_index("lane")


@pytest.fixture
def ring() -> Iterator[LaneChangeEnv]:
    env = LaneChangeEnv(ScenarioConfig.ring())
    yield env
    env.close()


def _episode(env: LaneChangeEnv, info: dict[str, Any], policy: Any) -> dict[str, Any]:
    """Run ``policy`` on the points until the episode ends; the last info."""
    done = False
    while not done:
        _obs, _r, terminated, truncated, info = env.step(policy(info["points"]))
        done = terminated or truncated
    return info


def _collision_seed(env: LaneChangeEnv) -> int:
    """A seed whose first episode ends in a collision when the ego changes lanes at once."""
    for seed in range(30):
        _obs, info = env.reset(seed=seed)
        if _episode(env, info, immediate_policy)["event"] == "collision":
            return seed
    raise AssertionError("no collision in 30 seeds with the immediate policy")


def _rollout(env: LaneChangeEnv, seed: int, n_steps: int) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """(obs, reward, points) of ``n_steps`` random-action steps from reset(seed), unseeded resets between."""
    actions = np.random.default_rng(seed).integers(0, 3, size=n_steps)
    obs, info = env.reset(seed=seed)
    out = [(obs, 0.0, info["points"])]
    for a in actions:
        obs, r, terminated, truncated, info = env.step(int(a))
        out.append((obs, r, info["points"]))
        if terminated or truncated:
            obs, info = env.reset()
            out.append((obs, 0.0, info["points"]))
    return out


def _lane_vehicles(env: LaneChangeEnv) -> dict[str, tuple[str, float, float]]:
    v = env.api.vehicle
    return {vid: (v.getLaneID(vid), v.getLanePosition(vid), v.getSpeed(vid)) for vid in v.getIDList()}


def test_seeded_reset_after_collisions_and_replays_equals_a_fresh_start() -> None:
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        seed = _collision_seed(env)
        _obs, info = env.reset(seed=seed)
        events = []
        while len(events) < 5 or events[-1] != "collision":  # builds and re-placements, ending in a collision
            events.append(_episode(env, info, immediate_policy)["event"])
            if events[-1] != "collision" or len(events) < 5:
                _obs, info = env.reset()
            assert len(events) < 40
        used = _rollout(env, seed=42, n_steps=120)
    finally:
        env.close()
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        fresh = _rollout(env, seed=42, n_steps=120)
    finally:
        env.close()
    assert len(used) == len(fresh) > 122  # episodes ended, so re-placements are part of the comparison
    for (obs_a, r_a, p_a), (obs_b, r_b, p_b) in zip(used, fresh):
        assert np.array_equal(obs_a, obs_b) and r_a == r_b and np.array_equal(p_a, p_b)


def _replay_capturing_the_placed_state(env: LaneChangeEnv, monkeypatch: pytest.MonkeyPatch) -> tuple[dict, dict]:
    """reset() -> (state of every vehicle just before the reset's simulation step, reset info)."""
    placed: list[dict[str, Any]] = []
    step = env._sim_step

    def snapshot_then_step() -> None:
        v = env.api.vehicle
        lc = {vid: v.getParameter(vid, "laneChangeModel.keepRightProbability") for vid in v.getIDList()}
        placed.append({vid: (*state, lc[vid]) for vid, state in _lane_vehicles(env).items()})
        step()

    monkeypatch.setattr(env, "_sim_step", snapshot_then_step)
    _obs, info = env.reset()
    monkeypatch.undo()
    assert len(placed) == 1  # one simulation step: no build
    return placed[0], info


def test_replayed_start_does_not_depend_on_how_the_last_episode_ended(monkeypatch) -> None:
    """After a collision (the ego's lane change still pending) or after a quiet time limit, a
    re-placement puts back the same state; only SUMO's random stream (driver imperfection in the
    one step that follows) differs, so the first observations agree up to that."""
    starts = []
    for policy, event in ((immediate_policy, "collision"), (keep_policy, "time_limit")):
        env = LaneChangeEnv(ScenarioConfig.ring())
        try:
            seed = _collision_seed(env)
            _obs, info = env.reset(seed=seed)
            assert _episode(env, info, policy)["event"] == event
            placed, info = _replay_capturing_the_placed_state(env, monkeypatch)
            assert env._episodes_since_load == 2 and info["lane"] == env.config.ego_lane
            _obs, _r, _te, _tr, after = env.step(0)
            assert after["lane"] == env.config.ego_lane  # no lane change left over from the last episode
            starts.append((placed, env.neighbour_ids(), info["points"]))
        finally:
            env.close()
    (placed_a, slots_a, points_a), (placed_b, slots_b, points_b) = starts
    assert placed_a == placed_b
    assert slots_a == slots_b
    np.testing.assert_allclose(points_a, points_b, atol=0.2)  # one step of dawdling: |dv| <= 0.13 m/s


def _lane_lists_in_order(env: LaneChangeEnv) -> bool:
    """SUMO's per-lane vehicle lists in position order (what its car following relies on)."""
    v = env.api.vehicle
    for lane in env.api.lane.getIDList():
        positions = [v.getLanePosition(vid) for vid in env.api.lane.getLastStepVehicleIDs(lane)]
        if positions != sorted(positions):
            return False
    return True


def test_replay_puts_the_ego_lane_back_and_rotates_the_other_lane(ring: LaneChangeEnv, monkeypatch) -> None:
    recorded: list[dict[str, tuple[str, float, float]]] = []
    warmup = ring._warmup

    def warmup_then_snapshot(seconds: float, min_steps: int = 0) -> None:
        warmup(seconds, min_steps)
        recorded.append(_lane_vehicles(ring))

    monkeypatch.setattr(ring, "_warmup", warmup_then_snapshot)
    ring.reset(seed=5)
    monkeypatch.undo()
    built = recorded[0]  # the end of the build's warm-up, what a re-placement puts back
    step = ring._sim_step
    placed_states: list[tuple[dict[str, tuple[str, float, float]], bool]] = []

    def snapshot_then_step() -> None:  # the re-placed state, before the reset's one step
        placed_states.append((_lane_vehicles(ring), _lane_lists_in_order(ring)))
        step()

    lap = ring._loop_length
    ego_lane = f"_{ring.config.ego_lane}"
    inner = sorted(vid for vid, (lane, _p, _s) in built.items() if not lane.endswith(ego_lane))

    def arc(lane: str, pos: float) -> float:
        return ring._offsets[lane.rsplit("_", 1)[0]] + pos

    for _ in range(ring.config.ring_rebuild_every - 1):
        _episode(ring, {"points": None}, lambda _p: 0)
        placed_states.clear()
        monkeypatch.setattr(ring, "_sim_step", snapshot_then_step)
        ring.reset()
        monkeypatch.undo()
        placed, in_order = placed_states[0]
        # SUMO's moveTo onto a vehicle's current lane leaves that lane's list unsorted unless avoided
        assert in_order
        assert placed.keys() == built.keys()
        for vid, (lane, pos, speed) in built.items():
            if vid not in inner:
                assert placed[vid] == (lane, pos, speed), vid  # the ego's lane exactly as built
            else:
                assert placed[vid][0][-2:] == lane[-2:] and placed[vid][2] == speed, vid
        shifts = np.array([(arc(*placed[v][:2]) - arc(*built[v][:2])) % lap for v in inner])
        shifts = np.unwrap(shifts / lap * 2 * np.pi) * lap / (2 * np.pi)
        # one rotation for the whole lane (up to 0.3 m where a vehicle would land inside a junction)
        assert np.ptp(shifts) < 0.35
        leader = ring.api.vehicle.getLeader(ring.ego_id, 30.0)
        assert not leader or not leader[0] or leader[1] >= 0.0


def test_unseeded_resets_keep_the_lane_counts_of_their_build() -> None:
    """Between builds the lanes do not drift: with the traffic left running they equalise (~14 / 14)
    within one episode, far outside the configured ranges."""
    cfg = ScenarioConfig.ring()
    env = LaneChangeEnv(cfg)
    try:
        _obs, info = env.reset(seed=0)
        build_counts = None
        for _ in range(12):
            lanes = [env.api.vehicle.getLaneIndex(v) for v in env.api.vehicle.getIDList() if v != env.ego_id]
            counts = tuple(np.bincount(lanes, minlength=2))
            if env._episodes_since_load == 1:
                build_counts = counts
            assert counts == build_counts
            outer, inner = cfg.ring_outer_vehicles, cfg.ring_inner_vehicles
            # (a background vehicle may change lanes during the build's 5 s warm-up)
            assert outer[0] - 1 <= counts[0] <= outer[1] + 1 and inner[0] - 1 <= counts[1] <= inner[1] + 1, counts
            _episode(env, info, keep_policy)
            _obs, info = env.reset()
    finally:
        env.close()


@pytest.mark.parametrize("every", [1, 4])
def test_rebuilds_every_k_episodes_and_replays_run_one_step_and_no_load(every: int, monkeypatch) -> None:
    env = LaneChangeEnv(ScenarioConfig.ring(ring_rebuild_every=every, max_episode_steps=3))
    try:
        calls = {"load": 0, "step": 0}
        load, step = env.sim.load, env.api.simulationStep

        def counting_load(args: list[str]) -> None:
            calls["load"] += 1
            load(args)

        def counting_step(*a: Any) -> None:
            calls["step"] += 1
            step(*a)

        monkeypatch.setattr(env.sim, "load", counting_load)
        monkeypatch.setattr(env.api, "simulationStep", counting_step)
        _obs, info = env.reset(seed=1)
        kinds = []
        for _ in range(9):
            _episode(env, info, keep_policy)
            calls.update(load=0, step=0)
            _obs, info = env.reset()
            kinds.append("build" if calls["load"] else "replay")
            if kinds[-1] == "replay":
                assert calls["step"] == 1  # the one step after the re-placement, no warm-up
        expected = ["build"] * 9 if every == 1 else (["replay"] * 3 + ["build"]) * 2 + ["replay"]
        assert kinds == expected
        calls.update(load=0, step=0)
        env.reset(seed=1)  # a seeded reset always builds, also right after a build or a re-placement
        assert calls["load"] == 1
    finally:
        env.close()
