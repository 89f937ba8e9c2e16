"""Sample efficiency in ``der table3`` (issue 44, point 5): the success AUC and the steps to 90% of the best final
success, read from run folders written the way a run writes them; the verdict on DER from the CIs; ``--name``."""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from der_ros import cli
from der_ros.experiments import sample_efficiency
from der_ros.experiments.aggregate import Interval, probability_of_improvement, verdict
from der_ros.experiments.sample_efficiency import efficiency_section, steps_to_reach, success_auc
from der_ros.experiments.suite import RunResult, RunSpec, methods_by_name
from der_ros.train.eval_result import EVALUATIONS_CSV, FINAL_EVAL_JSON, EpisodeResult, EvalResult, write_eval_row

S = 1_000_000_000
LABELS = {m.name: m.label for m in methods_by_name(None)} | {
    m.name + "+shield": m.label + " + shield" for m in methods_by_name(None)}  # fmt: skip


@pytest.fixture(autouse=True)
def _fewer_resamples(monkeypatch: pytest.MonkeyPatch) -> None:
    """Real rliable CIs, on 300 resamples instead of 2,000 (the verdicts below are clear-cut or far from 0.5)."""
    monkeypatch.setattr(sample_efficiency, "probability_of_improvement",
                        functools.partial(probability_of_improvement, reps=300))  # fmt: skip


def _eval(step: int, rate: float, n: int = 100) -> EvalResult:
    k = round(rate * n)
    return EvalResult(step=step, seeds=[S + i for i in range(n)], episodes=[
        EpisodeResult(seed=S + i, stream=i, ret=1.0, length=5, outcome="success" if i < k else "time_limit")
        for i in range(n)])  # fmt: skip


def _run(folder: Path, method: str, seed: int, curve: list[tuple[int, float]], final_n: int = 300) -> RunResult:
    """A finished run folder as the runner leaves it: one ``evaluations.csv`` row per evaluation (the last is the
    final one, on more episodes, also in ``evaluation.json``), ``episodes.csv`` and ``summary.json``."""
    run_dir = folder / method / f"seed{seed}"
    run_dir.mkdir(parents=True)
    for i, (step, rate) in enumerate(curve):
        last = i == len(curve) - 1
        ev = _eval(step, rate, final_n if last else 100)
        write_eval_row(run_dir / EVALUATIONS_CSV, ev)
        if last:
            ev.save(run_dir / FINAL_EVAL_JSON)
    (run_dir / "episodes.csv").write_text("episode,step,return,length,wall_time\n1,50,10.0,50,0.1\n")
    summary = {"steps": curve[-1][0], "interrupted": False, "wall_time_s": 1.0}
    (run_dir / "summary.json").write_text(json.dumps(summary))
    spec = RunSpec(method=methods_by_name(["dqn"])[0], seed=seed, config_path="config/exit.yaml", run_dir=str(run_dir),
                   group="exit")  # fmt: skip
    return RunResult(spec=spec, summary=summary, episode_steps=np.array([50.0]), returns=np.array([10.0]))


def _payload(runs: dict[str, list[RunResult]]) -> dict[str, dict]:
    """What write_table3 has in hand before the section: per method its seeds and final successes."""
    return {m: {"seeds": [r.spec.seed for r in rs],
                "eval_success": [EvalResult.load(Path(r.spec.run_dir) / FINAL_EVAL_JSON).success_rate for r in rs]}
            for m, rs in runs.items()}  # fmt: skip


def test_success_auc_is_the_trapezoid_over_the_step_span() -> None:
    # 2500·(0 + 0.5)/2 + 2500·(0.5 + 1)/2 + 10000·(1 + 0.9)/2 = 625 + 1875 + 9500 = 12000, over 15000 steps
    assert success_auc([0, 2500, 5000, 15000], [0.0, 0.5, 1.0, 0.9]) == pytest.approx(0.8)
    assert success_auc([0, 1000], [1.0, 1.0]) == pytest.approx(1.0)
    # the span, not the last step: (1000·0.3 + 1000·0.4) / 2000
    assert success_auc([1000, 2000, 3000], [0.2, 0.4, 0.4]) == pytest.approx(0.35)
    assert math.isnan(success_auc([15000], [0.9]))  # one evaluation has no area


def test_the_json_holds_each_runs_auc_and_its_first_step_at_90_percent_of_the_best(tmp_path: Path) -> None:
    """Best final success: DER λ 0.9 (IQM 1.0), so τ = 0.9 for the unshielded methods. Seed 1 of DQN reaches
    exactly 0.9 at step 5000 (>= counts); seed 2 never does and is censored at its budget, 7500. The shielded
    group has its own best (IQM 0.6), τ = 0.54."""
    runs = {
        "dqn": [_run(tmp_path, "dqn", 1, [(0, 0.0), (2500, 0.88), (5000, 0.9), (7500, 0.8)]),
                _run(tmp_path, "dqn", 2, [(0, 0.0), (2500, 0.5), (5000, 0.8), (7500, 0.8)])],
        "der0.9": [_run(tmp_path, "der0.9", 1, [(0, 0.2), (2500, 0.95), (5000, 1.0), (7500, 1.0)]),
                   _run(tmp_path, "der0.9", 2, [(0, 0.0), (2500, 1.0), (5000, 1.0), (7500, 1.0)])],
        "dqn+shield": [_run(tmp_path, "dqn+shield", 1, [(0, 0.0), (2500, 0.55), (5000, 0.6), (7500, 0.6)])],
    }  # fmt: skip
    payload = _payload(runs)
    lines = efficiency_section(runs, payload, LABELS)
    dqn = payload["dqn"]
    # (2500·0.88/2 + 2500·1.78/2 + 2500·1.7/2) / 7500 = (1100 + 2225 + 2125) / 7500
    assert dqn["eval_success_auc"] == pytest.approx([5450 / 7500, (625 + 1625 + 2000) / 7500])
    assert dqn["eval_steps_to_90"] == [5000.0, 7500.0] and dqn["eval_reached_90"] == [True, False]
    assert payload["der0.9"]["eval_steps_to_90"] == [2500.0, 2500.0]
    se = dqn["sample_efficiency"]
    assert se["steps_to_90_threshold"] == pytest.approx(0.9) and se["steps_to_90_best_method"] == "der0.9"
    assert (se["not_reached_90"], se["runs_90"]) == (1, 2)
    assert se["steps_to_90_iqm"][0] == pytest.approx(6250.0)  # the censored run counts at its budget
    assert payload["dqn+shield"]["sample_efficiency"]["steps_to_90_threshold"] == pytest.approx(0.54)
    assert payload["dqn+shield"]["eval_steps_to_90"] == [2500.0]
    assert "| DQN (n=2) | " in "\n".join(lines) and "| 0.900 (λ = 0.9) | 1/2 |" in "\n".join(lines)
    # λ 0.9 against DQN from 2 seeds each: the P(X > Y) is there, the verdict is not (fewer than 5 seeds)
    vs = payload["der0.9"]["sample_efficiency"]["vs"]
    assert set(vs) == {"dqn"} and vs["dqn"]["verdict_eval_success"] is None and vs["dqn"]["poi_eval_success"][0] == 1.0
    # the rule itself: no success reaches a threshold of 0 (undefined), and a run below it gets its budget
    assert math.isnan(steps_to_reach([0, 10], [0.0, 0.0], 0.0).step)
    assert steps_to_reach([0, 10, 20], [0.1, 0.2, 0.3], 0.5) == sample_efficiency.Reach(20.0, False)


def test_the_verdict_follows_the_ci_not_the_point_estimate() -> None:
    assert verdict(Interval(0.9, 0.6, 1.0), 10) == "better"
    assert verdict(Interval(0.1, 0.0, 0.45), 10) == "worse"
    assert verdict(Interval(0.7, 0.45, 0.9), 10) == "indistinguishable"  # point above 0.5, CI includes it
    assert verdict(Interval(0.9, 0.6, 1.0), 4) is None  # too few seeds for a CI
    assert verdict(Interval(math.nan, math.nan, math.nan), 10) is None


def test_the_verdict_sentence_says_better_worse_or_indistinguishable_on_final_success_and_on_auc(tmp_path: Path) -> None:
    """Five seeds each, curves (0, 0) → (1000, mid) → (2000, final): AUC = (2·mid + final) / 4. λ 0.1 ends higher than
    DQN on every seed but learns late (mid 0): better on final success, worse on AUC. λ 0.5 is below DQN on both.
    λ 0.9 interleaves with DQN: indistinguishable on both. Shielded twins with too few seeds get no verdict."""
    finals = {"dqn": [0.60, 0.62, 0.64, 0.66, 0.68], "per": [0.61, 0.63, 0.65, 0.67, 0.69],
              "der0.1": [0.90, 0.91, 0.92, 0.93, 0.94], "der0.5": [0.30, 0.31, 0.32, 0.33, 0.34],
              "der0.9": [0.59, 0.63, 0.62, 0.67, 0.66]}  # fmt: skip
    mids = {"der0.1": 0.0}
    runs = {m: [_run(tmp_path, m, k, [(0, 0.0), (1000, mids.get(m, 0.5)), (2000, f)]) for k, f in enumerate(fs)]
            for m, fs in finals.items()}  # fmt: skip
    runs |= {m + "+shield": [_run(tmp_path, m + "+shield", 0, [(0, 0.0), (2000, 0.5)])] for m in ("dqn", "der0.9")}
    payload = _payload(runs)
    text = "\n".join(efficiency_section(runs, payload, LABELS))
    bullets = {line.split(":")[0][2:]: line for line in text.splitlines() if line.startswith("- ")}
    assert bullets["λ = 0.1 against DQN"].startswith("- λ = 0.1 against DQN: better on final success (P = 1.00 "
                                                     "[1.00, 1.00]); worse on success AUC (P = 0.00 [0.00, 0.00]).")  # fmt: skip
    assert "worse on final success" in bullets["λ = 0.5 against PER"] and "worse on success AUC" in bullets["λ = 0.5 against PER"]
    assert "indistinguishable on final success" in bullets["λ = 0.9 against DQN"]
    assert "indistinguishable on success AUC" in bullets["λ = 0.9 against DQN"]
    assert "no verdict on final success" in bullets["λ = 0.9 + shield against DQN + shield"]
    assert ("\non final success, better in 2 of 7 comparisons, worse in 2, indistinguishable in 2, no verdict in 1 "
            "(fewer than 5 seeds on a side);\non success AUC, better in 0 of 7 comparisons, worse in 4, "
            "indistinguishable in 2, no verdict in 1 (fewer than 5 seeds on a side).\n") in text  # fmt: skip
    vs = payload["der0.1"]["sample_efficiency"]["vs"]["dqn"]
    assert (vs["verdict_eval_success"], vs["verdict_eval_success_auc"]) == ("better", "worse")
    assert vs["poi_eval_success"] == [1.0, 1.0, 1.0]
    # steps to 90% (τ = 0.9 · 0.92 = 0.828): λ 0.1 reaches it at its final evaluation, step 2000, DQN never does
    # (censored at the same 2000, but ranked behind): P(λ 0.1 in fewer steps) = 1; λ 0.5 and DQN never do: a tie
    assert payload["der0.1"]["eval_steps_to_90"] == payload["dqn"]["eval_steps_to_90"] == [2000.0] * 5
    assert payload["der0.1"]["eval_reached_90"] == [True] * 5 and payload["dqn"]["eval_reached_90"] == [False] * 5
    assert vs["poi_fewer_eval_steps_to_90"] == [1.0, 1.0, 1.0]
    assert payload["der0.5"]["sample_efficiency"]["vs"]["dqn"]["poi_fewer_eval_steps_to_90"] == [0.5, 0.5, 0.5]
    row = next(line for line in text.splitlines() if line.startswith("| λ = 0.1 (n=5) | 0.230 ["))  # AUC 0.92 / 4
    assert row.endswith("] | 2000 [2000, 2000] | 0.828 (λ = 0.1) | 0/5 |"), row
    assert "| DQN (n=5) | 0.410 [" in text and "] | 2000 [2000, 2000] | 0.828 (λ = 0.1) | 5/5 |" in text


def _exit_runs(out: Path) -> None:
    for m in ("dqn", "der0.9"):
        _run(out / "exit", m, 1000, [(0, 0.0), (150, 0.4), (300, 0.7 if m == "dqn" else 0.8)])


def test_name_writes_the_named_files_and_records_it_in_the_command(tmp_path: Path) -> None:
    out, results = tmp_path / "runs", tmp_path / "results"
    _exit_runs(out)
    argv = ["table3", "--networks", "exit", "--methods", "dqn", "der0.9", "--seeds", "1", "--steps", "300",
            "--no-train", "--no-baselines", "--out", str(out), "--results", str(results), "--name", "table_exit"]  # fmt: skip
    assert cli.main(argv) == 0
    assert sorted(p.name for p in results.iterdir()) == ["table_exit.json", "table_exit.md", "table_exit_exit_curves.png"]
    md = (results / "table_exit.md").read_text()
    assert "--name table_exit" in md and "](table_exit_exit_curves.png)" in md
    data = json.loads((results / "table_exit.json").read_text())["exit"]
    assert data["dqn"]["eval_success_auc"] == pytest.approx([(150 * 0.4 / 2 + 150 * 1.1 / 2) / 300])
    assert data["der0.9"]["sample_efficiency"]["steps_to_90_threshold"] == pytest.approx(0.72)


@pytest.mark.parametrize("bad", ["../table_exit", "table_exit.md", "a b", "-x", ""])
def test_a_bad_name_is_refused_with_one_line_before_anything_runs(tmp_path: Path, bad: str) -> None:
    argv = ["table3", "--networks", "exit", "--seeds", "1", "--out", str(tmp_path / "runs"),
            "--results", str(tmp_path / "results"), f"--name={bad}"]  # fmt: skip
    with pytest.raises(SystemExit) as err:
        cli.main(argv)
    message = str(err.value.code)
    assert message.startswith(f"der table3: --name {bad!r}, expected a plain file stem") and "\n" not in message
    assert not (tmp_path / "runs").exists() and not (tmp_path / "results").exists()
