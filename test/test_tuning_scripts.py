"""The helper scripts under results/tuning/ that the tuning notes cite run as documented."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BASELINES = REPO / "results" / "tuning" / "baselines_tuning_seeds.py"


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
