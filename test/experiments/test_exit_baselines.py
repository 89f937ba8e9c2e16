"""The exit's rule baselines run through the baselines path: the ego really gets the rule's driver (IDM
vType, tuned lane-change parameters), and ``der baselines config/exit.yaml --only mobil sumo_tuned``
evaluates both on exit episodes (slow: SUMO episodes with warm-ups)."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros import cli
from der_ros.experiments.baselines import MOBIL_EGO_TYPE, rule_params

REPO = Path(__file__).resolve().parents[2]
EXIT = REPO / "config" / "exit.yaml"


def test_the_taken_over_ego_gets_the_rules_vtype_and_lane_change_parameters() -> None:
    env = gym.make("der_ros/LaneChangeScenario-v0", scenario={
        "file": "exit", "ego_type": MOBIL_EGO_TYPE, "ego_lane_change_params": ["lcAssertive=3.5", "lcStrategic=2"]})  # fmt: skip
    try:
        env.reset(seed=1500000000)
        u = env.unwrapped
        api, ego = u.api, u.ego_id
        assert api.vehicle.getTypeID(ego) == MOBIL_EGO_TYPE
        assert float(api.vehicle.getParameter(ego, "laneChangeModel.lcAssertive")) == 3.5
        assert float(api.vehicle.getParameter(ego, "laneChangeModel.lcStrategic")) == 2.0
        env.reset()  # the next ego (an unseeded reset takes over another car) gets them too
        assert u.ego_id != ego and api.vehicle.getTypeID(u.ego_id) == MOBIL_EGO_TYPE
        assert float(api.vehicle.getParameter(u.ego_id, "laneChangeModel.lcAssertive")) == 3.5
    finally:
        env.close()


@pytest.mark.slow
def test_der_baselines_runs_mobil_and_sumo_tuned_on_exit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["baselines", str(EXIT), "--only", "mobil", "sumo_tuned", "--episodes", "3", "--jobs", "1",
                     "--tuning-seeds", "--out", str(tmp_path)]) == 0  # fmt: skip
    rows = [[c.strip() for c in x.strip().strip("|").split("|")] for x in capsys.readouterr().out.splitlines()
            if x.startswith("| der_ros/")]  # fmt: skip
    assert [r[1] for r in rows] == ["mobil", "sumo_tuned"]
    for row in rows:
        name = row[1]
        folder = tmp_path / "tuning-seeds" / "exit" / name
        eps = json.loads((folder / "evaluation.json").read_text())["episodes"]
        assert int(row[2]) == len(eps) == 3
        assert float(row[3]) == pytest.approx(sum(e["outcome"] == "success" for e in eps) / 3, abs=0.0005)
        assert float(row[6]) == pytest.approx(sum(e["outcome"] == "missed" for e in eps) / 3, abs=0.0005)
        assert all(e["outcome"] in ("success", "missed", "collision", "time_limit") for e in eps)
        meta = json.loads((folder / "baseline.json").read_text())
        frozen = rule_params(name, "exit")
        assert meta["params"] == (frozen if name == "sumo_tuned" else frozen.__dict__ | {"idm": frozen.idm.__dict__})


def test_random_baseline_draws_every_action_of_the_env() -> None:
    """On exit (five actions) `random` draws the speed actions too; without n_actions it keeps the paper's three."""
    from der_ros.experiments.baselines import baseline_policy

    obs, infos = [None] * 400, [{"points": None}] * 400
    assert set(baseline_policy("random", seed=1, n_actions=5)(obs, infos)) == {0, 1, 2, 3, 4}
    assert set(baseline_policy("random", seed=1)(obs, infos)) == {0, 1, 2}
    # same seed, three actions: the ring's and urban's draws are what they were
    assert baseline_policy("random", seed=1, n_actions=3)(obs, infos) == baseline_policy("random", seed=1)(obs, infos)
