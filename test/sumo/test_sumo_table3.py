"""Table 3 plumbing: a short SUMO training run logs episode events and its greedy evaluation; the
table reads them back. Real training (tiny), real env, real files."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from der_ros.experiments.suite import PAPER_METHODS, load_result, plan_runs
from der_ros.experiments.table3 import PAPER_TABLE3, score_run, write_table3
from der_ros.train.config import load_experiment_config
from der_ros.train.runner import train

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_short_ring_run_logs_events_and_table3_reports_them(tmp_path: Path) -> None:
    method = PAPER_METHODS[3]  # DER lambda = 0.9
    (spec,) = plan_runs(REPO / "config" / "ring.yaml", [method], [0], tmp_path / "runs", group="ring")
    overrides = {
        **dict(method.overrides),
        "train.total_steps": 120,
        "train.seed": 0,
        "train.progress": False,
        "train.tensorboard": False,
        "train.save_final_checkpoint": False,
        "agent.learning_starts": 64,
        "agent.batch_size": 32,
        "train.eval_interval": 0,
        "train.final_eval_episodes": 3,
    }
    cfg = load_experiment_config(spec.config_path, overrides)
    train(cfg, run_dir=spec.run_dir)

    with open(Path(spec.run_dir) / "episodes.csv", newline="") as fh:
        n_episodes = sum(1 for _ in csv.DictReader(fh))
    assert n_episodes >= 3  # random actions on the ring end episodes quickly (seed 0: 4 since re-placed resets, 5 before)

    run = load_result(spec, ("charts/episode_success", "charts/episode_collision"))
    succ = run.metrics["charts/episode_success"][1]
    coll = run.metrics["charts/episode_collision"][1]
    assert len(succ) == len(coll) == n_episodes  # one event row per finished episode
    assert set(succ.tolist()) <= {0.0, 1.0} and not any(succ * coll)  # an episode is one or the other
    scores = score_run(run)
    assert scores["train_total_reward"] == pytest.approx(run.returns.mean())
    final = run.spec.run_dir + "/evaluation.json"
    summary = json.loads(Path(final).read_text())["summary"]
    assert scores["eval_success"] == pytest.approx(summary["success"])
    assert scores["eval_collision"] == pytest.approx(summary["collision"])
    assert scores["eval_return"] == pytest.approx(summary["mean_return"]) and scores["eval_episodes"] == 3

    md, js = write_table3({"ring": {method.name: [run]}}, {method.name: method.label}, {}, tmp_path / "table3.md",
                          "der table3 ...", [0], {"ring": 120}, 1.0)  # fmt: skip
    text = md.read_text()
    assert f"{PAPER_TABLE3['ring']['der0.9']:.2f}" in text
    assert f"| ring | λ = 0.9 | 0 | {scores['eval_success']:.3f} | {scores['eval_collision']:.3f} " in text
    assert f"{scores['train_total_reward']:.2f}" in text and "eclipse-sumo" in text
    assert json.loads(js.read_text())["ring"]["der0.9"]["seeds"] == [0]

    # --urban-seeds: urban ran fewer seeds than ring; the runs section says how many per network
    md2, js2 = write_table3({"ring": {method.name: [run, run]}, "urban": {method.name: [run]}},
                            {method.name: method.label}, {}, tmp_path / "mixed" / "table3.md", "der table3 ...",
                            [0, 1], {"ring": 120, "urban": 120}, 1.0)  # fmt: skip
    assert "(2 per method; runs per network: ring 2, urban 1)" in md2.read_text()
    assert [len(v["der0.9"]["eval_success"]) for v in json.loads(js2.read_text()).values()] == [2, 1]


@pytest.mark.slow
def test_urban_seeds_out_of_range_is_refused_before_any_run(tmp_path: Path) -> None:
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "der_ros.cli", "table3", "--seeds", "3", "--urban-seeds", "4",
                          "--out", str(tmp_path / "runs"), "--results", str(tmp_path)],
                         cwd=REPO, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode != 0 and "--urban-seeds = 4, expected 1..3" in out.stderr + out.stdout
    assert not (tmp_path / "runs").exists()
