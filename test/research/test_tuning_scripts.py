"""The helper scripts under research/tuning/ that the tuning notes cite run as documented."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # trains and runs SUMO: minutes on a loaded 2-core machine

REPO = Path(__file__).resolve().parents[2]
BASELINES = REPO / "research" / "tuning" / "baselines_tuning_seeds.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(BASELINES), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300)  # fmt: skip


def test_baselines_on_tuning_seeds_counts_outcomes() -> None:
    # never changing lane can only run into the time limit: 2 episodes, both time limits, no caused collision
    out = _run(str(REPO / "config" / "ring.yaml"), "--baselines", "keep", "--episodes", "2")
    assert out.returncode == 0, out.stderr
    assert "keep: 2 episodes, {'time_limit': 2}" in out.stdout
    assert "caused-collision seeds []" in out.stdout


def test_baselines_on_tuning_seeds_refuses_a_non_sumo_config() -> None:
    out = _run(str(REPO / "config" / "cartpole.yaml"), "--episodes", "2")
    assert out.returncode != 0
    assert "is not a SUMO lane-change env" in out.stderr


PROBE = REPO / "research" / "tuning" / "boundary_probe.py"


def test_boundary_probe_collects_labelled_changes_and_scores_a_run(tmp_path: Path) -> None:
    import numpy as np

    data = tmp_path / "boundary.npz"
    out = subprocess.run([sys.executable, str(PROBE), "collect", str(REPO / "config" / "ring.yaml"), "--changes", "4",
                          "--out", str(data)], cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr
    d = np.load(data)
    n = len(d["collided"])
    assert d["collided"].dtype == bool and 0 < n <= 4 and d["points"].shape[0] == n
    assert f"{n} lane changes, {int(d['collided'].sum())} caused a collision" in out.stdout

    run = tmp_path / "run"  # a tiny training run: what `score` reads is its checkpoint.pt and config.yaml
    train = subprocess.run([sys.executable, "-m", "der_ros.cli", "train", "--config", str(REPO / "config" / "ring.yaml"),
                            "--set", "train.total_steps=20", "--set", "agent.learning_starts=10",
                            "--set", "train.eval_interval=0", "--set", "train.final_eval_episodes=1",
                            "--set", f"train.run_dir={run}", "--set", "train.progress=false"],
                           cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert train.returncode == 0, train.stderr
    out = subprocess.run([sys.executable, str(PROBE), "score", str(data), str(run)], cwd=REPO, capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr
    bad, safe = (int(x) for x in out.stdout.splitlines()[-1].split(": ")[1].replace(" colliding changes taken,", "")
                 .replace(" safe ones", "").split())  # fmt: skip
    assert 0 <= bad <= int(d["collided"].sum()) and 0 <= safe <= n - int(d["collided"].sum())


def test_boundary_probe_refuses_a_non_sumo_config(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(PROBE), "collect", str(REPO / "config" / "cartpole.yaml"), "--changes",
                          "2", "--out", str(tmp_path / "x.npz")], cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode != 0
    assert "is not a SUMO lane-change env" in out.stderr
