"""config/baselines.yaml: thresholds per network, and whether they were tuned (the tables say so)."""

from __future__ import annotations

from pathlib import Path

import pytest

from der_ros.configuration import ConfigError
from der_ros.experiments.baselines import gap_params_tuned, load_gap_params
from der_ros.experiments.table3 import write_table3

REPO = Path(__file__).resolve().parents[2]


def test_tuned_flag_defaults_to_true_and_is_not_a_threshold(tmp_path: Path) -> None:
    assert gap_params_tuned("ring") and gap_params_tuned("urban")  # the shipped file: both tuned
    f = tmp_path / "b.yaml"
    f.write_text("gap_acceptance:\n  urban: {lead_gap: 2, follow_gap: 3, time_headway: 1, tuned: false}\n")
    assert not gap_params_tuned("urban", f)
    assert load_gap_params("urban", f).lead_gap == 2.0  # 'tuned' is not a threshold


def test_bad_tuned_flag_and_unknown_keys_are_named(tmp_path: Path) -> None:
    f = tmp_path / "b.yaml"
    f.write_text("gap_acceptance:\n  ring: {lead_gap: 1, follow_gap: 1, time_headway: 1, tuned: maybe}\n")
    with pytest.raises(ConfigError, match=r"gap_acceptance.ring.tuned = 'maybe'"):
        gap_params_tuned("ring", f)
    f.write_text("gap_acceptance:\n  ring: {lead_gap: 1, follow_gap: 1, time_headway: 1, tunned: true}\n")
    with pytest.raises(ConfigError, match=r"unknown keys \['tunned'\]"):
        load_gap_params("ring", f)


def test_table3_labels_an_untuned_gap_rule(tmp_path: Path) -> None:
    from der_ros.train.eval_result import EpisodeResult, EvalResult

    res = EvalResult(step=0, episodes=[EpisodeResult(seed=1, stream=0, ret=200.0, length=50, outcome="success",
                                                     caused=False)], seeds=[1], wall_s=0.1)  # fmt: skip
    md, _ = write_table3({"urban": {}}, {}, {"urban": {"gap_acceptance": res}}, tmp_path / "t.md", "der table3",
                         [1], {"urban": 1}, 0.0, {"urban": {"gap_acceptance": "gap acceptance (not tuned)"}})  # fmt: skip
    text = md.read_text()
    assert "| *baseline:* gap acceptance (not tuned) | 1.000 |" in text and "(tuned)" not in text
