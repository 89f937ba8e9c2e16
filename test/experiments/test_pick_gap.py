"""The gap-acceptance tuning's choice (der_ros.experiments.baselines.pick_gap)."""

from __future__ import annotations

import pytest

from der_ros.experiments.baselines import GAP_GRID, GapAcceptanceParams, pick_gap
from der_ros.train.eval_result import EpisodeResult, EvalResult


def _result(success: int, caused: int, n: int = 100) -> EvalResult:
    eps = [EpisodeResult(seed=k, stream=k, ret=200.0, length=50, outcome="success") for k in range(success)]
    eps += [
        EpisodeResult(seed=k, stream=k, ret=-100.0, length=5, outcome="collision", caused=True) for k in range(caused)
    ]
    eps += [
        EpisodeResult(seed=k, stream=k, ret=100.0, length=50, outcome="time_limit") for k in range(n - success - caused)
    ]
    return EvalResult(step=0, episodes=eps, seeds=list(range(n)))


def test_the_best_setting_causes_no_collision_by_default() -> None:
    safe, risky = GapAcceptanceParams(0.5, 1.0, 1.0), GapAcceptanceParams(0.0, 0.0, 0.25)
    scored = [(safe, _result(95, 0)), (risky, _result(99, 1))]
    assert pick_gap(scored)[0] == safe  # one caused collision in 100 disqualifies the riskier rule
    assert pick_gap(scored, max_collision=0.01)[0] == risky  # the old 1% allowance would take it


def test_ties_go_to_fewer_collisions_and_no_qualifier_falls_back_to_all() -> None:
    a, b = GapAcceptanceParams(0.0, 0.0, 0.5), GapAcceptanceParams(1.0, 2.0, 1.0)
    assert pick_gap([(a, _result(97, 2)), (b, _result(97, 1))], max_collision=0.05)[0] == b
    assert pick_gap([(a, _result(90, 3)), (b, _result(80, 2))])[0] == a  # none is collision-free
    with pytest.raises(ValueError, match="no scored settings"):
        pick_gap([])


def test_the_grid_holds_the_previous_ring_rule_and_zero_margins() -> None:
    lead, follow, headway = GAP_GRID["lead_gap"], GAP_GRID["follow_gap"], GAP_GRID["time_headway"]
    assert 0.5 in lead and 1.0 in follow and 1.0 in headway  # the rule tuned 2026-11-26
    assert 0.0 in lead and 0.0 in follow and 0.5 in headway  # the edge found on 6,000 tuning situations
