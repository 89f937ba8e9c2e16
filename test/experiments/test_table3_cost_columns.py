"""Table 3's success-at-what-cost columns (issue 44): ``eval_time_to_exit`` and ``eval_imposed_brake`` per seed
for learned methods and once per baseline, null (never 0) for evaluations made before they were measured, and
the archived runs behind results/table3.json re-tabled with every published field unchanged (the sample-efficiency
keys are the only ones added)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from der_ros.experiments import sample_efficiency, table3
from der_ros.experiments.aggregate import Interval
from der_ros.experiments.suite import PAPER_METHODS, RunResult, RunSpec, load_result, methods_by_name, shielded_method
from der_ros.experiments.table3 import write_table3
from der_ros.train.eval_result import FINAL_EVAL_JSON, EpisodeResult, EvalResult

REPO = Path(__file__).resolve().parents[2]
ARCHIVE = REPO / "research" / "run_files" / "table3"
S = 1_000_000_000
SAMPLE_EFFICIENCY_KEYS = {"eval_success_auc", "eval_steps_to_90", "eval_reached_90", "sample_efficiency"}


def _ev(eps: list[tuple[str, float | None, float | None]]) -> EvalResult:
    return EvalResult(step=0, seeds=[S + i for i in range(len(eps))], episodes=[
        EpisodeResult(seed=S + i, stream=i, ret=1.0, length=5, outcome=o, time_to_success=t, imposed_brake=b)
        for i, (o, t, b) in enumerate(eps)])  # fmt: skip


def test_the_json_and_the_table_carry_the_cost_fields_and_null_for_older_evaluations(tmp_path: Path) -> None:
    method = PAPER_METHODS[0]
    evals = {1000: _ev([("success", 4.0, 2.0), ("success", 6.0, 5.0), ("time_limit", None, 0.0)]),
             1001: _ev([("success", None, None), ("collision", None, None)])}  # written before the metrics  # fmt: skip
    runs = []
    for seed, ev in evals.items():
        run_dir = tmp_path / f"seed{seed}"
        run_dir.mkdir()
        ev.save(run_dir / FINAL_EVAL_JSON)
        spec = RunSpec(method=method, seed=seed, config_path="config/exit.yaml", run_dir=str(run_dir), group="exit")
        runs.append(RunResult(spec=spec, summary={"steps": 10}, episode_steps=np.zeros(1), returns=np.zeros(1)))
    baselines = {"sumo": _ev([("success", 10.0, 4.5), ("success", 12.0, 3.5)]),
                 "keep": _ev([("time_limit", None, 0.0)]), "random": _ev([("success", None, None)])}  # fmt: skip
    md, js = write_table3({"exit": {method.name: runs}}, {method.name: method.label}, {"exit": baselines},
                          tmp_path / "table_exit.md", "der table3", list(evals), {"exit": 10}, 0.0)  # fmt: skip
    data = json.loads(js.read_text())["exit"]
    assert data[method.name]["eval_time_to_exit"] == [pytest.approx(5.0), None]
    assert data[method.name]["eval_imposed_brake"] == [pytest.approx(7.0 / 3), None]
    assert (data["sumo"]["eval_time_to_exit"], data["sumo"]["eval_imposed_brake"]) == (11.0, 4.0)
    assert data["keep"]["eval_time_to_exit"] is None and data["keep"]["eval_imposed_brake"] == 0.0
    assert data["random"]["eval_time_to_exit"] is None and data["random"]["eval_imposed_brake"] is None
    text = md.read_text()
    assert "| Time to success (s) | Imposed braking (m/s²) |" in text
    assert "| *baseline:* SUMO's own model (standing request) | 1.000 | 0.000 | 0.000 | 1.0 | 0.00 | 11.0 | 4.0 |" in text
    assert "| *baseline:* never change (keep) | 0.000 | 0.000 | 1.000 | 1.0 | 0.00 | – | 0.0 |" in text
    assert "| *baseline:* random | 1.000 | 0.000 | 0.000 | 1.0 | 0.00 | – | – |" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {method.label} (n=2)"))
    assert re.search(r"\| 5\.0 ± 0\.0 \| 2\.3 ± 0\.0 \|", row), row  # the one seed that has them
    assert "| exit | DQN | 1000 | 0.667 | 0.000 | 0.333 | 1.00 | 5.0 | 2.3 |" in text
    assert "| exit | DQN | 1001 | 0.500 | 0.000 | 0.000 | 1.00 | – | – |" in text


def _cheap(scores: Any, *args: Any, **kwargs: Any) -> Interval:
    """A stand-in for the bootstrap CIs: the JSON holds per-seed values only, the markdown is not compared."""
    x = np.asarray(scores, dtype=np.float64)
    x = x[~np.isnan(x)]
    v = float(x.mean()) if x.size else float("nan")
    return Interval(v, v, v)


def test_the_archived_runs_re_table_with_every_published_field_unchanged(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    """research/run_files/table3 (the runs behind results/table3.json): every field of the published JSON
    comes back the same. The paper's rows were made before the cost metrics (null for every method and
    baseline); the ring's shielded rows were trained partly after (their later seeds carry them)."""
    for name in ("iqm_interval", "mean_interval", "probability_of_improvement"):
        monkeypatch.setattr(table3, name, _cheap)
    for name in ("iqm_interval", "probability_of_improvement"):
        monkeypatch.setattr(sample_efficiency, name, _cheap)
    monkeypatch.setattr(table3, "_paired", lambda *args, **kwargs: [])
    published = json.loads((REPO / "results" / "table3.json").read_text())
    paper = methods_by_name(["dqn", "der0.1", "der0.5", "der0.9", "per"])
    methods = {m.name: m for m in paper + [shielded_method(m, "rss") for m in paper]}
    results: dict[str, dict[str, list[RunResult]]] = {}
    baselines: dict[str, dict[str, EvalResult]] = {}
    for net in ("ring", "urban"):
        results[net] = {}
        for name, method in methods.items():
            specs = [RunSpec(method=method, seed=int(d.name[4:]), config_path=f"config/{net}.yaml", run_dir=str(d),
                             group=net) for d in sorted((ARCHIVE / net / name).glob("seed*"))]  # fmt: skip
            if specs:
                results[net][name] = [load_result(spec, ()) for spec in specs]
        baselines[net] = {d.name: EvalResult.load(d / FINAL_EVAL_JSON) for d in sorted((ARCHIVE / net / "baselines").iterdir())}
    assert set(results["ring"]) == set(methods) and set(results["urban"]) == {m.name for m in paper}
    _md, js = write_table3(results, {m: methods[m].label for m in methods}, baselines, tmp_path / "table3.md",
                           "der table3", list(range(1000, 1010)), {"ring": 15000, "urban": 15000}, 0.0)  # fmt: skip
    again = json.loads(js.read_text())
    compared = 0
    for net, by_name in published.items():
        assert set(again[net]) == set(by_name), net
        for name, fields in by_name.items():
            added = set(again[net][name]) - set(fields)  # new keys only: the sample efficiency of learned methods
            assert set(fields) <= set(again[net][name]), (net, name)
            assert added == (SAMPLE_EFFICIENCY_KEYS if "seeds" in fields else set()), (net, name, added)
            for key, value in fields.items():
                assert json.dumps(again[net][name][key]) == json.dumps(value), (net, name, key)
                compared += 1
            if "+shield" not in name:
                cost = [again[net][name][k] for k in table3.COST_KEYS]
                assert cost == ([[None] * 10] * 2 if "seeds" in fields else [None, None]), (net, name, cost)
    assert compared > 110  # the 110 fields of the paper's rows and the baselines, and the shielded rows'
