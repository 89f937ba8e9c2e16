"""Scenarios as data (issue 44): the loader's errors, ring/urban as files give the code-built episodes,
a user's scenario from files in test/scenarios/tiny trains and evaluates, speed actions.

One libsumo simulation per process: every test closes its env before the next opens.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from der_ros import cli
from der_ros.configuration import to_dict
from der_ros.train.config import load_experiment_config
from der_ros.train.runner import train
from sumo_bridge import SCENARIO_ENV_ID
from sumo_bridge.lane_change_env import LaneChangeEnv, make_scenario_env
from sumo_bridge.scenario import ScenarioConfig
from sumo_bridge.scenario_file import ScenarioFileError, load_scenario, load_scenario_config, shipped_scenario
from sumo_bridge.sim_backend import libsumo_in_use

TINY = Path(__file__).resolve().parents[1] / "scenarios" / "tiny"


def _episodes(env: gym.Env, seeds: list[int], episodes_per_seed: int = 2) -> list[tuple[Any, ...]]:
    """Observations, rewards and events of a fixed action pattern (change after 3 decisions), seeded
    resets followed by unseeded ones (the training stream's reset paths)."""
    out: list[tuple[Any, ...]] = []
    for seed in seeds:
        for k in range(episodes_per_seed):
            obs, _info = env.reset(seed=seed if k == 0 else None)
            rows = [obs.tobytes()]
            t, done = 0, False
            while not done:
                obs, r, term, trunc, info = env.step(1 if t % 4 == 3 else 0)
                rows.append((obs.tobytes(), r, info["event"], info["lane"]))
                t, done = t + 1, term or trunc
            out.append(tuple(rows))
    return out


@pytest.mark.parametrize("name", ["ring", pytest.param("urban", marks=pytest.mark.slow)])  # urban: ~6 s, full run only
def test_builtin_scenario_files_give_the_code_built_episodes(name: str) -> None:
    """sumo_bridge/scenarios/{ring,urban}.yaml are ScenarioConfig.ring()/.urban(): same config, and the
    same episodes (observations, rewards, events) through der_ros/LaneChangeScenario-v0 as through the
    code-built config, computed here on pinned seeds."""
    code = getattr(ScenarioConfig, name)()
    assert load_scenario_config(name) == code
    seeds = [3, 11] if name == "ring" else [5]
    env = LaneChangeEnv(code)
    try:
        expected = _episodes(env, seeds)
    finally:
        env.close()
    env = gym.make(SCENARIO_ENV_ID, scenario=str(shipped_scenario(name))).unwrapped
    try:
        assert env.config == code
        got = _episodes(env, seeds)
    finally:
        env.close()
    assert got == expected
    assert len({e[-1][2] for e in got}) >= 1 and all(e[-1][2] is not None for e in got)


def _write(tmp_path: Path, text: str) -> Path:
    for f in TINY.iterdir():
        if f.suffix == ".xml":
            shutil.copy(f, tmp_path / f.name)
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


_GOOD = (TINY / "tiny.yaml").read_text()


@pytest.mark.parametrize(
    "text, field",
    [
        (_GOOD.replace("nodes: tiny.nod.xml", "nodes: missing.nod.xml"), "network.nodes"),
        (_GOOD.replace("lane: leftmost", "lane: 7"), "ego.lane"),
        (_GOOD.replace("goal: {edge: ramp}", "goal: {edge: main}"), "goal.edge"),
        (_GOOD.replace("goal: {edge: ramp}", "goal: {edge: nowhere}"), "goal.edge"),
        (_GOOD.replace("route: [approach, ramp]", "route: [approach, bridge]"), "ego.route"),
        (_GOOD.replace("horizon: 40", "horizon: [40"), "line"),
        (_GOOD.replace("horizon: 40", "horizon: -4"), "horizon"),
        (_GOOD.replace("actions: [keep, left, right, faster, slower]", "actions: [keep, brake]"), "actions"),
        (_GOOD.replace("settings: {success_ends_episode:", "settings: {sucess_ends_episode:"),
         "settings.sucess_ends_episode"),
        (_GOOD.replace("network: {nodes: tiny.nod.xml, edges: tiny.edg.xml, connections: tiny.con.xml}\n", ""),
         "network"),
        (_GOOD + "safety: {brake_min: 0}\n", "safety.brake_min"),
        (_GOOD + "safety: {unobserved_speed: fast}\n", "safety.unobserved_speed"),
        (_GOOD + "safety: {response_time: -0.1}\n", "safety.response_time"),
        (_GOOD + "safety: {brake_max: .nan}\n", "safety.brake_max"),
        (_GOOD + "safety: {margin: 1}\n", "safety.margin"),
        (_GOOD + "safety: 7\n", "safety"),
        (_GOOD + "safety: {lane_end: 1}\n", "safety.lane_end"),
    ],
    ids=["missing-network", "unknown-lane", "goal-unreachable", "goal-not-on-route", "unknown-edge", "bad-yaml",
         "bad-horizon", "bad-actions", "unknown-setting", "no-network", "safety-zero-brake", "safety-not-a-number",
         "safety-negative", "safety-nan", "safety-unknown-key", "safety-not-a-mapping", "safety-lane-end-not-bool"],
)
def test_malformed_scenario_files_give_one_line_naming_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    assert text != _GOOD  # the mistake was made
    path = _write(tmp_path, text)
    with pytest.raises(ScenarioFileError) as err:
        load_scenario(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message
    if field == "line":
        assert f"{path}:" in message and "not valid YAML" in message
    else:
        assert f": {field}:" in message
        assert message.startswith(f"{path}:")  # with the line where the key is
    assert libsumo_in_use() is None  # nothing was started


def test_safety_section_is_read_and_optional(tmp_path: Path) -> None:
    """A scenario's ``safety:`` section: the keys it gives, nothing else; none in ring/urban; exit states its
    trucks' emergency braking and the unobserved car's speed (docs/safety.md, "The exit scenario")."""
    path = _write(tmp_path, _GOOD + "safety: {brake_min: 7, unobserved_speed: 30.5}\n")
    assert load_scenario(path).safety == {"brake_min": 7.0, "unobserved_speed": 30.5}
    assert load_scenario(TINY / "tiny.yaml").safety == {}
    assert load_scenario(shipped_scenario("ring")).safety == {} == load_scenario(shipped_scenario("urban")).safety
    assert load_scenario(shipped_scenario("exit")).safety == {"unobserved_speed": 25.0, "lane_end": True}


def test_der_train_with_a_bad_scenario_file_fails_before_sumo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = _write(tmp_path, _GOOD.replace("lane: leftmost", "lane: 9"))
    cfg = tmp_path / "exp.yaml"
    cfg.write_text(f"env: {{id: {SCENARIO_ENV_ID}, kwargs: {{scenario: {{file: {bad}}}}}}}\n")
    code = cli.main(["train", "--config", str(cfg), "--run-dir", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code != 0 and "ego.lane" in err and str(bad) in err
    assert libsumo_in_use() is None and not (tmp_path / "run" / "metrics.csv").exists()


def test_tiny_user_scenario_passes_check_env_and_has_speed_actions() -> None:
    from gymnasium.utils.env_checker import check_env

    env = make_scenario_env(scenario={"file": str(TINY / "tiny.yaml")})  # no spec: check_env would re-make it
    try:
        assert env.action_space.n == 5 and env.action_meanings[3:] == ("faster", "slower")
        check_env(env, skip_render_check=True)
        obs, info = env.reset(seed=1)
        # the last entry: the distance to the diverge (ego row's gap) over goal_distance_scale
        to_split = env._goal_distance(*env._ego_road_pos_speed[:2])
        assert 0.0 < to_split <= 200.0 and info["points"][0, 5] == to_split
        assert obs.shape == (30,) and obs[-1] == pytest.approx(to_split / 200.0)
        speed = env._ego_road_pos_speed[2]
        env.step(4)  # slower: the target speed steps down from the current speed
        assert env._target_speed == pytest.approx(max(speed - env.config.speed_step, 0.0))
        env.step(3)
        env.step(3)  # faster twice: one step above the first target
        assert env._target_speed == pytest.approx(min(speed + env.config.speed_step, 25.0))
        with pytest.raises(ValueError, match="expected one of 0 \\(keep\\)"):
            env.step(5)
        # seeded resets are pure functions of the seed (the warmed state per traffic seed)
        a = _episodes(env, [7], 1)
        b = _episodes(env, [7], 1)
        assert a == b
    finally:
        env.close()


def test_warmed_state_does_not_depend_on_what_the_process_ran_before() -> None:
    """A traffic seed's saved state is the same whether it is the first thing the process makes or comes
    after other episodes (sumo_bridge.traffic_state): SUMO's RNG counters at save time once carried the
    process's history, so a cache filled in another order continued the traffic with other draws."""
    from sumo_bridge.traffic_state import state_body

    env = make_scenario_env(scenario={"file": str(TINY / "tiny.yaml")})
    try:
        env.reset(seed=3)
        seed_of_5 = int(np.random.default_rng(5).integers(0, 2**31 - 1))  # the env's first draw after reset(seed=5)
        env.reset(seed=5)
        first = env._state_file(seed_of_5)
        body = state_body(first)
        for _ in range(3):  # more history: episodes on other traffic seeds
            env.reset(seed=11)
            for _t in range(20):
                env.step(0)
        first.unlink()
        env.reset(seed=5)  # the state is made again, after all that
        assert first.is_file() and state_body(first) == body
        assert 'name="seed"' in body or "rng" in body.lower()  # the state carries the RNG (the point of the test)
    finally:
        env.close()


def test_three_action_scenario_refuses_speed_actions() -> None:
    env = gym.make(SCENARIO_ENV_ID, scenario={"file": str(TINY / "tiny.yaml"), "actions": ["keep", "left", "right"]}).unwrapped
    try:
        assert env.action_space.n == 3
        env.reset(seed=0)
        with pytest.raises(ValueError):
            env.step(3)
    finally:
        env.close()


def test_tiny_user_scenario_trains_and_evaluates_in_process(tmp_path: Path) -> None:
    cfg = load_experiment_config(None, {
        "env.id": SCENARIO_ENV_ID,
        "env.kwargs": {"scenario": {"file": str(TINY / "tiny.yaml")}},
        "train.total_steps": 300, "train.seed": 0, "train.device": "cpu", "train.eval_interval": 150,
        "train.eval_episodes": 2, "train.final_eval_episodes": 4, "agent.learning_starts": 50,
        "agent.batch_size": 32, "agent.hidden_sizes": [32], "agent.epsilon_decay_steps": 200,
        "replay.kind": "der", "replay.capacity": 1000, "replay.h2_capacity": 200,
    })  # fmt: skip
    summary = train(cfg, run_dir=tmp_path / "tiny")
    assert summary.steps == 300
    final = json.loads((tmp_path / "tiny" / "evaluation.json").read_text())
    outcomes = [e["outcome"] for e in final["episodes"]]
    assert len(outcomes) == 4 and set(outcomes) <= {"success", "collision", "time_limit", "missed"}
    saved = load_experiment_config(tmp_path / "tiny" / "config.yaml")
    assert saved.env.kwargs["scenario"]["file"] == str(TINY / "tiny.yaml")
    assert to_dict(load_scenario_config(TINY / "tiny.yaml"))["network"] == "tiny"
    assert libsumo_in_use() is None


def test_bridge_gate_refuses_actions_the_scenario_lacks() -> None:
    from sumo_bridge.lockstep import CommandGate, Verdict

    for n_actions, ok in ((3, False), (5, True)):
        gate = CommandGate(n_actions=n_actions)
        gate.open(1)
        verdict, _ = gate.offer(1, [4], sender="agent")
        assert (verdict is Verdict.ACCEPTED) == ok
        assert gate.counters[Verdict.OUT_OF_RANGE.value] == (0 if ok else 1)


def test_der_graph_scenario_path_sets_the_bridge_and_agent_parameters(tmp_path: Path) -> None:
    from der_ros.graph.snapshot_evaluation import scenario_env_config
    from der_ros.nodes.params import build_graph_params

    params = build_graph_params({}, steps=100, scenario=str(TINY / "tiny.yaml"), run_dir=tmp_path)
    bridge = params["bridge_node"]["ros__parameters"]
    assert bridge["scenario.network"] == "tiny" and bridge["scenario.file"] == str(TINY / "tiny.yaml")
    assert bridge["scenario.actions"] == ["keep", "left", "right", "faster", "slower"]
    assert params["agent_node"]["ros__parameters"]["n_actions"] == 5
    assert params["agent_node"]["ros__parameters"]["observation.goal_distance_scale"] == 200.0
    env_cfg = scenario_env_config(bridge)
    assert env_cfg.id == SCENARIO_ENV_ID and env_cfg.kwargs["scenario"]["file"] == str(TINY / "tiny.yaml")
    with pytest.raises(ScenarioFileError):
        build_graph_params({}, steps=100, scenario=str(tmp_path / "nope.yaml"), run_dir=tmp_path)
    # the scenario's safety section reaches the safety node, where it is the more cautious value
    shield = build_graph_params({}, steps=100, scenario="exit", run_dir=tmp_path)["safety_node"]["ros__parameters"]
    assert (shield["safety.unobserved_speed"], shield["safety.lane_end"]) == (25.0, True) and "safety.brake_min" not in shield
    base = {"safety_node": {"ros__parameters": {"safety": {"brake_min": 4.5, "unobserved_speed": 20.0}}}}
    shield = build_graph_params(base, steps=100, scenario="exit", run_dir=tmp_path)["safety_node"]["ros__parameters"]
    assert (shield["safety.brake_min"], shield["safety.unobserved_speed"]) == (4.5, 25.0)
    assert shield["n_actions"] == 5  # exit's speed actions pass the safety node like keep lane
    assert "safety.unobserved_speed" not in params["safety_node"]["ros__parameters"]  # tiny has no section
