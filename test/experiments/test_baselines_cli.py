"""Smoke tests of ``der baselines`` and ``der baselines --tune`` (issue 45: nothing ran them): the printed
numbers are recounted from each baseline's own cached episodes, and the tuned setting is re-picked by hand
from the tuning table."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from der_ros import cli
from der_ros.experiments import baselines

REPO = Path(__file__).resolve().parents[2]
RING = REPO / "config" / "ring.yaml"


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_der_baselines_prints_each_baselines_own_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["baselines", str(RING), "--episodes", "2", "--jobs", "2", "--out", str(tmp_path)]) == 0
    rows = [_cells(x) for x in capsys.readouterr().out.splitlines() if x.startswith("| der_ros/")]
    assert [r[1] for r in rows] == list(baselines.SUMO_BASELINES)
    for _env_id, name, n, success, collision, time_limit, missed, ret, interventions, tts, brake in rows:
        eps = json.loads((tmp_path / "ring" / name / "evaluation.json").read_text())["episodes"]
        # success at what cost to others: each episode's own, averaged (time: over the successful ones)
        times = [e["time_to_success"] for e in eps if e["outcome"] == "success"]
        assert tts == (f"{sum(times) / len(times):.2f}" if times else "–")
        assert float(brake) == pytest.approx(sum(e["imposed_brake"] for e in eps) / 2, abs=0.005)
        assert int(n) == len(eps) == 2
        assert float(success) == pytest.approx(sum(e["outcome"] == "success" for e in eps) / 2)
        assert float(collision) == pytest.approx(sum(e["outcome"] == "collision" and e["caused"] for e in eps) / 2)
        assert float(time_limit) == pytest.approx(sum(e["outcome"] == "time_limit" for e in eps) / 2)
        assert float(ret) == pytest.approx(sum(e["ret"] for e in eps) / 2, abs=0.005)
        assert float(missed) == 0.0  # the ring has no exit to miss
        assert float(interventions) == 0.0  # no shield asked for: nothing vetoed
    keep = next(r for r in rows if r[1] == "keep")
    assert (keep[3], keep[5]) == ("0.000", "1.000")  # never changes lane: never arrives, always the time limit
    assert (keep[9], keep[10]) == ("–", "0.00")  # no success to time, nobody made to brake


def test_der_baselines_tune_picks_the_best_safe_setting(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(baselines, "GAP_GRID", {"lead_gap": (0.0, 8.0), "follow_gap": (0.0,), "time_headway": (0.5,)})
    assert cli.main(["baselines", str(RING), "--tune", "--episodes", "2", "--jobs", "2", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "tuning" / "gap_acceptance_ring.md").read_text()
    assert md.strip() == capsys.readouterr().out.strip()
    rows = [[float(c) for c in _cells(x)] for x in md.splitlines() if re.match(r"^\| [0-9]", x)]
    assert sorted((r[0], r[1], r[2]) for r in rows) == [(0.0, 0.0, 0.5), (8.0, 0.0, 0.5)]
    safe = [r for r in rows if r[4] == 0.0] or rows  # no caused collision, else all
    best = max(safe, key=lambda r: (r[3], -r[4], r[5]))
    picked = re.search(r"Best: `\{follow_gap: ([0-9.]+), lead_gap: ([0-9.]+), time_headway: ([0-9.]+)\}`", md)
    assert picked is not None, md
    assert (float(picked[2]), float(picked[1]), float(picked[3])) == (best[0], best[1], best[2])
