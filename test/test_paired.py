"""Learned runs paired with a baseline episode by episode (der_ros.experiments.paired) and the table section built on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from der_ros.experiments.paired import paired_counts
from der_ros.experiments.suite import PAPER_METHODS, RunResult, RunSpec
from der_ros.experiments.table3 import write_table3
from der_ros.train.evaluation import FINAL_EVAL_JSON, EpisodeResult, EvalResult

S = 1_000_000_000


def _ev(outcomes: list[tuple[int | None, str, bool]]) -> EvalResult:
    eps = [EpisodeResult(seed=seed, stream=i, ret=0.0, length=1, outcome=o, caused=c)
           for i, (seed, o, c) in enumerate(outcomes)]  # fmt: skip
    return EvalResult(step=0, episodes=eps, seeds=[s for s, _, _ in outcomes if s is not None])


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
    # a collision someone else caused is not the method's
    assert paired_counts([_ev([(S + 3, "collision", False)])], base).method_caused == 0  # type: ignore[union-attr]
    assert paired_counts([_ev([(S + 7, "success", False)])], base) is None


def test_table3_pairs_learned_runs_with_the_gap_rule_and_sumo(tmp_path: Path) -> None:
    method = PAPER_METHODS[0]
    runs = []
    for seed, outcomes in ((0, [(S, "collision", True), (S + 1, "success", False)]),
                           (1, [(S, "success", False), (S + 1, "success", False)])):  # fmt: skip
        run_dir = tmp_path / f"seed{seed}"
        run_dir.mkdir()
        _ev(outcomes).save(run_dir / FINAL_EVAL_JSON)
        spec = RunSpec(method=method, seed=seed, config_path="config/ring.yaml", run_dir=str(run_dir), group="ring")
        runs.append(RunResult(spec=spec, summary={"steps": 10}, episode_steps=np.zeros(1), returns=np.zeros(1)))
    gap = _ev([(S, "success", False), (S + 1, "time_limit", False)])
    sumo = _ev([(S, "success", False), (S + 1, "success", False)])
    md, _ = write_table3({"ring": {method.name: runs}}, {method.name: method.label},
                         {"ring": {"gap_acceptance": gap, "sumo": sumo}}, tmp_path / "t.md", "der table3", [0, 1],
                         {"ring": 10}, 0.0)  # fmt: skip
    text = md.read_text()
    assert "(the episodes that start from a seeded reset, 2 per run)" in text
    assert "| DQN | gap acceptance (tuned) | 4 | 2 | 1 | 1 (1) | 1 | 0 |" in text
    assert "| DQN | SUMO's own model (standing request) | 4 | 0 | 1 | 1 (1) | 1 | 0 |" in text
    assert ("- Against gap acceptance (tuned): each learned method succeeds in 2 pairs where the baseline fails, "
            "the baseline in 1 where the method fails; a method's caused collisions (1) fall in 1 distinct traffic "
            "situation, and the baseline gets through every one of them.") in text  # fmt: skip
