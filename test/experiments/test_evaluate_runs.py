"""``der evaluate`` (was der_ros/experiments/evaluate_runs.py (der evaluate)): a run's checkpoint re-evaluated greedily on more seeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from der_ros.cli import main as der_main
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE

pytestmark = pytest.mark.slow  # trains and runs SUMO: minutes on a loaded 2-core machine

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny CartPole run with a final greedy evaluation on the first 3 report seeds."""
    run = tmp_path_factory.mktemp("evaluate") / "cartpole" / "seed0"
    assert der_main(["train", "--config", str(REPO / "config" / "cartpole.yaml"), "--set", "train.total_steps=200",
                     "--set", "agent.learning_starts=50", "--set", "train.eval_interval=0",
                     "--set", "train.final_eval_episodes=3", "--set", f"train.run_dir={run}",
                     "--set", "train.progress=false"]) == 0  # fmt: skip
    return run


def test_report_seeds_reproduce_the_runs_own_final_evaluation(run_dir: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    out = tmp_path / "out"
    assert der_main(["evaluate", str(run_dir), "--episodes", "3", "--seed-set", "report", "--out", str(out)]) == 0
    again = EvalResult.load(out / "cartpole" / "seed0" / "evaluation.json")
    own = EvalResult.load(run_dir / "evaluation.json")
    assert again.seeds == own.seeds == [EVAL_SEED_BASE + k for k in range(3)]
    assert [(e.seed, e.ret, e.length, e.outcome) for e in again.episodes] == \
        [(e.seed, e.ret, e.length, e.outcome) for e in own.episodes]  # fmt: skip
    text = capsys.readouterr().out
    assert f"{run_dir}: 3 episodes, success 0, caused collision 0 (seeds []), time limit 0" in text
    assert "total over 1 runs: {'terminated': 3}" in text


def test_tuning_seeds_by_default_and_more_episodes(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert der_main(["evaluate", str(run_dir), "--episodes", "5", "--out", str(out)]) == 0
    doc = json.loads((out / "cartpole" / "seed0" / "evaluation.json").read_text())
    assert doc["seeds"] == [TUNING_EVAL_SEED_BASE + k for k in range(5)] and len(doc["episodes"]) == 5


def test_a_directory_without_a_checkpoint_is_one_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert der_main(["evaluate", str(tmp_path), "--episodes", "2"]) == 2
    assert f"{tmp_path / 'config.yaml'}: not found" in capsys.readouterr().err
