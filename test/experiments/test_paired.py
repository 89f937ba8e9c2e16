"""Learned runs paired with a baseline episode by episode (der_ros.experiments.paired) and the table section built on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from der_ros.experiments.paired import paired_counts
from der_ros.experiments.stats import paired_permutation_p
from der_ros.experiments.suite import PAPER_METHODS, RunResult, RunSpec
from der_ros.experiments.table3 import write_table3
from der_ros.train.eval_result import FINAL_EVAL_JSON, EpisodeResult, EvalResult

S = 1_000_000_000


def _ev(outcomes: list[tuple[int | None, str, bool]]) -> EvalResult:
    eps = [EpisodeResult(seed=seed, stream=i, ret=0.0, length=1, outcome=o, caused=c)
           for i, (seed, o, c) in enumerate(outcomes)]  # fmt: skip
    return EvalResult(step=0, episodes=eps, seeds=[s for s, _, _ in outcomes if s is not None])


def _table(tmp_path: Path, per_seed: dict[int, list[tuple[int | None, str, bool]]],
           baselines: dict[str, EvalResult]) -> str:  # fmt: skip
    method = PAPER_METHODS[0]
    runs = []
    for seed, outcomes in per_seed.items():
        run_dir = tmp_path / f"seed{seed}"
        run_dir.mkdir()
        _ev(outcomes).save(run_dir / FINAL_EVAL_JSON)
        spec = RunSpec(method=method, seed=seed, config_path="config/ring.yaml", run_dir=str(run_dir), group="ring")
        runs.append(RunResult(spec=spec, summary={"steps": 10}, episode_steps=np.zeros(1), returns=np.zeros(1)))
    md, _ = write_table3({"ring": {method.name: runs}}, {method.name: method.label}, {"ring": baselines},
                         tmp_path / "t.md", "der table3", list(per_seed), {"ring": 10}, 0.0)  # fmt: skip
    return md.read_text()


def test_counts_pair_episodes_by_seed_and_skip_unseeded_follow_ups() -> None:
    base = _ev([(S, "success", False), (S + 1, "time_limit", False), (S + 2, "success", False),
                (S + 3, "collision", True)])  # fmt: skip
    run_a = _ev([(S, "collision", True), (S + 1, "success", False), (S + 2, "success", False),
                 (S + 3, "collision", False), (None, "collision", True)])  # fmt: skip
    run_b = _ev([(S + 3, "success", False), (S, "collision", True), (S + 9, "success", False)])  # order does not matter
    c = paired_counts([run_a, run_b], base)
    assert c is not None
    assert (c.runs, c.pairs) == (2, 6)  # the unseeded follow-up and the seed the baseline never saw are left out
    assert (c.only_method, c.only_baseline) == (2, 2)  # a: S+1 / S; b: S+3 / S
    assert (c.method_caused, c.method_caused_situations, c.method_caused_baseline_succeeds) == (2, 1, 2)
    assert c.baseline_caused == 2  # S+3, paired once in each run
    # by situation: S (both runs collide where the baseline succeeds) is worse on success and on caused
    # collisions; S+1 (a succeeds, the baseline times out) and S+3 (b succeeds, the baseline caused a
    # collision) are better on success, and S+3 has fewer caused collisions; S+2 is a tie
    assert c.situations == 4
    assert c.success_diffs == (-1.0, 1.0, 0.0, 0.5)  # in seed order: S, S+1, S+2, S+3
    assert c.caused_diffs == (-1.0, 0.0, 0.0, 1.0)
    assert (c.success_better, c.success_worse, c.caused_fewer, c.caused_more) == (2, 1, 1, 1)
    assert c.success_p == 1.0  # every sign assignment of (1, 1, 0.5) sums at least 0.5 away from zero
    assert c.caused_p == 1.0
    # a collision someone else caused is not the method's
    assert paired_counts([_ev([(S + 3, "collision", False)])], base).method_caused == 0  # type: ignore[union-attr]
    assert paired_counts([_ev([(S + 7, "success", False)])], base) is None


@pytest.mark.slow
def test_table3_pairs_learned_runs_with_the_gap_rule_and_sumo(tmp_path: Path) -> None:
    gap = _ev([(S, "success", False), (S + 1, "time_limit", False)])
    sumo = _ev([(S, "success", False), (S + 1, "success", False)])
    text = _table(tmp_path, {0: [(S, "collision", True), (S + 1, "success", False)],
                             1: [(S, "success", False), (S + 1, "success", False)]},
                  {"gap_acceptance": gap, "sumo": sumo})  # fmt: skip
    assert "(the episodes that start from a seeded reset, 2 per run)" in text
    assert "| DQN | gap acceptance (tuned) | 4 | 2 | 1 | 1 (1) | 1 | 0 | 1 / 1 (1.000) | 0 / 1 (1.000) |" in text
    assert "| DQN | SUMO's own model (standing request) | 4 | 0 | 1 | 1 (1) | 1 | 0 | 0 / 1 (1.000) | 0 / 1 (1.000) |" in text
    assert ("- Against gap acceptance (tuned): each learned method succeeds in 2 pairs where the baseline fails, "
            "the baseline in 1 where the method fails; a method's caused collisions (1) fall in 1 distinct traffic "
            "situation, and the baseline gets through every one of them.") in text  # fmt: skip
    # two situations cannot make a sign test significant, and the section says so
    assert ("- Paired by traffic situation (permutation test, p < 0.05, uncorrected), against gap acceptance (tuned): "
            "no learned method differs on success or on caused collisions. On success or caused collisions no difference could "
            "show: it takes 6 situations all one way, and here at most 2 differ.") in text  # fmt: skip


def test_permutation_test_counts_sign_assignments_exactly_and_samples_reproducibly() -> None:
    assert paired_permutation_p([]) == paired_permutation_p([0.0, 0.0]) == 1.0
    assert paired_permutation_p([1.0] * 6) == paired_permutation_p([-0.3] * 6) == pytest.approx(2 / 64)
    # magnitudes count: three large gains against three small losses is not all one way
    # (sum 1.5 of 2.5: |sum| >= 1.5 when the flipped magnitudes add to <= 0.5 or >= 2.0, 8 + 8 of 64 subsets)
    assert paired_permutation_p([0.7, 0.7, 0.6, -0.2, -0.2, -0.1]) == pytest.approx(16 / 64)
    # above 16 differences the assignments are sampled, with a fixed generator
    many = [0.1] * 30 + [-0.1] * 10
    p = paired_permutation_p(many, resamples=20_000)
    assert p == paired_permutation_p(many, resamples=20_000)
    assert 0.001 < p < 0.01  # the exact two-sided p of 30 against 10 equal steps is 0.0022
    assert paired_permutation_p([1.0] * 40, resamples=999) == pytest.approx(1 / 1000)
    with pytest.raises(ValueError, match="resamples = 0"):
        paired_permutation_p([1.0], resamples=0)
    with pytest.raises(ValueError, match="finite"):
        paired_permutation_p([1.0, float("nan")])


@pytest.mark.slow
def test_table3_names_a_difference_by_situation_only_when_the_permutation_test_finds_one(tmp_path: Path) -> None:
    # the rule gets through six situations the agent fails in both runs: significant (p = 2/64)
    fails = [(S + k, "time_limit", False) for k in range(6)]
    rule = _ev([(S + k, "success", False) for k in range(6)])
    text = _table(tmp_path, {0: fails, 1: fails}, {"gap_acceptance": rule})
    assert "| DQN | gap acceptance (tuned) | 12 | 0 | 12 | 0 (0) | 0 | 0 | 0 / 6 (0.031) | 0 / 0 (1.000) |" in text
    assert ("- Paired by traffic situation (permutation test, p < 0.05, uncorrected), against gap acceptance (tuned): "
            "DQN is worse on success (0 against 6 situations, p = 0.031); no other difference.") in text  # fmt: skip
