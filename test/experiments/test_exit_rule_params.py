"""The exit's rule baselines: which baselines a scenario gets, the frozen mobil / sumo_tuned parameters in
config/baselines.yaml (one-line errors naming file and field), and the env settings each rule runs with."""

from __future__ import annotations

from pathlib import Path

import pytest

from der_ros.configuration import ConfigError
from der_ros.experiments import baselines
from der_ros.experiments.baselines import (
    EXIT_BASELINES,
    MOBIL_EGO_TYPE,
    SUMO_BASELINES,
    baseline_env_config,
    baseline_job,
    baseline_names,
    rule_params,
)
from der_ros.experiments.rule_params import load_mobil_params, load_sumo_tuned_params
from der_ros.train.config import load_experiment_config
from sumo_bridge.mobil import MobilParams
from sumo_bridge.scenario import ScenarioConfig, lane_change_params

REPO = Path(__file__).resolve().parents[2]


def test_exit_gets_the_seven_baselines_and_ring_and_urban_keep_theirs() -> None:
    assert baseline_names(load_experiment_config(REPO / "config" / "exit.yaml").env) == EXIT_BASELINES
    assert EXIT_BASELINES == ("keep", "immediate", "random", "gap_acceptance", "mobil", "sumo", "sumo_tuned")
    for net in ("ring", "urban"):
        assert baseline_names(load_experiment_config(REPO / "config" / f"{net}.yaml").env) == SUMO_BASELINES
    assert SUMO_BASELINES == ("keep", "immediate", "random", "gap_acceptance", "sumo")


def test_the_shipped_file_holds_the_exits_tuned_rules() -> None:
    mobil = rule_params("mobil", "exit")
    assert isinstance(mobil, MobilParams) and mobil.idm == MobilParams().idm
    tuned = rule_params("sumo_tuned", "exit")
    assert tuned and all(name.startswith("lc") for name in tuned)
    assert rule_params("gap_acceptance", "exit") == baselines.load_gap_params("exit")
    assert baselines.gap_params_tuned("exit")  # tuned on the tuning seeds: no 'tuned: false' left
    assert rule_params("keep", "exit") is None and rule_params("gap_acceptance+shield", "ring") is not None


@pytest.mark.parametrize(
    ("load", "text", "message"),
    [
        (load_mobil_params, "mobil:\n  ring: {exit_bias: 1}\n", r"b\.yaml: mobil\.exit missing, expected a mapping of MobilParams fields"),
        (load_mobil_params, "mobil:\n  exit: {exit_bais: 1}\n", r"b\.yaml: mobil\.exit: unknown keys \['exit_bais'\]"),
        (load_mobil_params, "mobil:\n  exit: {exit_bias: lots}\n", r"b\.yaml: mobil\.exit\.exit_bias = 'lots', expected a finite number"),
        (load_mobil_params, "mobil:\n  exit: {safe_decel: -4}\n", r"b\.yaml: mobil\.exit\.safe_decel = -4\.0, expected a value >= 0"),
        (load_mobil_params, "mobil:\n  exit: {exit_lookahead: 0}\n", r"b\.yaml: mobil\.exit\.exit_lookahead = 0\.0, expected a value > 0"),
        (load_mobil_params, "mobil: [exit]\n", r"b\.yaml: mobil = \['exit'\], expected a mapping of networks"),
        (load_sumo_tuned_params, "gap_acceptance: {}\n", r"b\.yaml: sumo_tuned\.exit missing, expected a mapping of SUMO lane-change parameters"),
        (load_sumo_tuned_params, "sumo_tuned:\n  exit: {lcAssertiv: 3}\n", r"b\.yaml: sumo_tuned\.exit: unknown keys \['lcAssertiv'\]"),
        (load_sumo_tuned_params, "sumo_tuned:\n  exit: {lcAssertive: .nan}\n", r"b\.yaml: sumo_tuned\.exit\.lcAssertive = nan, expected a finite"),
        (load_sumo_tuned_params, "sumo_tuned:\n  exit: {lcAssertive: 0}\n", r"b\.yaml: sumo_tuned\.exit\.lcAssertive = 0\.0, expected a value > 0"),
        (load_sumo_tuned_params, "sumo_tuned:\n  exit: {lcStrategic: true}\n", r"b\.yaml: sumo_tuned\.exit\.lcStrategic = True, expected a finite"),
        (load_sumo_tuned_params, "sumo_tuned:\n  exit: {}\n", r"b\.yaml: sumo_tuned\.exit is empty"),
    ],
)
def test_a_malformed_section_is_one_line_naming_file_and_field(tmp_path: Path, load, text: str, message: str) -> None:  # noqa: ANN001
    f = tmp_path / "b.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        load("exit", f)
    assert "\n" not in str(err.value)


def test_a_good_section_loads_with_the_rest_at_their_defaults(tmp_path: Path) -> None:
    f = tmp_path / "b.yaml"
    f.write_text("mobil:\n  exit: {exit_bias: 3, safe_decel: 6}\nsumo_tuned:\n  exit: {lcStrategic: 2, lcAssertive: 3}\n")
    m = load_mobil_params("exit", f)
    assert (m.exit_bias, m.safe_decel, m.politeness, m.threshold) == (3.0, 6.0, 0.5, 0.2)
    assert load_sumo_tuned_params("exit", f) == {"lcAssertive": 3.0, "lcStrategic": 2.0}


def test_each_rule_runs_with_its_own_ego() -> None:
    env = load_experiment_config(REPO / "config" / "exit.yaml").env
    assert baseline_env_config(env, "keep") is env
    mobil = baseline_env_config(env, "mobil", MobilParams())
    assert mobil.kwargs["scenario"]["ego_type"] == MOBIL_EGO_TYPE
    assert "ego_lane_change_mode" not in mobil.kwargs["scenario"]  # laneChangeMode 0: only MOBIL changes lanes
    tuned = baseline_env_config(env, "sumo_tuned", {"lcAssertive": 3.0, "lcStrategic": 2.0})
    assert tuned.kwargs["scenario"]["ego_lane_change_mode"] == baselines.SUMO_DEFAULT_LANE_CHANGE_MODE
    assert tuned.kwargs["scenario"]["ego_lane_change_params"] == ["lcAssertive=3.0", "lcStrategic=2.0"]
    assert env.kwargs["scenario"] == {"file": "exit"}  # the caller's config is not modified
    # the cached evaluation names the parameters it ran with, so another setting is evaluated afresh
    a = baseline_job(env, "sumo_tuned", 2, 1, 0, "x", {"lcAssertive": 3.0})
    b = baseline_job(env, "sumo_tuned", 2, 1, 0, "x", {"lcAssertive": 2.0})
    assert a.meta() != b.meta() and a.meta()["params"] == {"lcAssertive": 3.0}
    assert baseline_job(env, "mobil", 2, 1, 0, "x", MobilParams(exit_bias=3.0)).meta()["params"]["exit_bias"] == 3.0
    gap = baseline_job(env, "gap_acceptance", 2, 1, 0, "x", baselines.GapAcceptanceParams())
    assert gap.gap == baselines.GapAcceptanceParams() and "params" not in gap.meta()  # earlier caches stay valid


@pytest.mark.parametrize(
    ("entries", "message"),
    [
        (("lcAssertive",), r"'lcAssertive', expected 'name=value'"),
        (("lcBogus=1",), r"'lcBogus=1', expected 'name=value' with name one of lcStrategic"),
        (("lcAssertive=much",), r"'lcAssertive=much', expected a finite number after '='"),
    ],
)
def test_malformed_ego_lane_change_params_are_named(entries: tuple[str, ...], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        lane_change_params(entries)
    assert lane_change_params(("lcAssertive=3", "lcSpeedGain = 0.5")) == {"lcAssertive": 3.0, "lcSpeedGain": 0.5}


def test_the_ring_and_urban_set_ups_refuse_an_ego_driver() -> None:
    with pytest.raises(ConfigError, match=r"ego_type = 'ego_idm', expected it empty: only scenario files"):
        ScenarioConfig.ring(ego_type="ego_idm")
    with pytest.raises(ConfigError, match=r"ego_lane_change_params = \('lcAssertive=3',\), expected it empty"):
        ScenarioConfig.urban(ego_lane_change_params=("lcAssertive=3",))
