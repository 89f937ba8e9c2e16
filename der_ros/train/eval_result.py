"""What an evaluation produces, and its files: one episode, one evaluation (``evaluation.json``,
:class:`EvalResult`), and a run's log of evaluations (``evaluations.csv``)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "OUTCOMES",
    "EpisodeResult",
    "EvalResult",
    "write_eval_row",
    "read_evaluations",
    "truncate_evaluations",
    "EVALUATIONS_CSV",
    "FINAL_EVAL_JSON",
]

#: Episode outcomes: the SUMO env's ``info["event"]``; other envs 'terminated' / 'time_limit'.
OUTCOMES = ("success", "collision", "time_limit", "terminated", "missed")  # missed: a file scenario's exit

EVALUATIONS_CSV = "evaluations.csv"
FINAL_EVAL_JSON = "evaluation.json"


@dataclass
class EpisodeResult:
    """One evaluation episode."""

    seed: int | None  # the seed of the reset that began its stream (None: an unseeded follow-up)
    stream: int  # index of the seeded stream it belongs to
    ret: float
    length: int
    outcome: str  # one of OUTCOMES
    caused: bool = False  # a collision the agent caused (SUMO env)
    interventions: int = 0  # commands the safety shield replaced by keep lane (env.safety, docs/safety.md)
    #: seconds from the episode's start to its success (SUMO env, ``info["time_to_success"]``); None when it did
    #: not succeed, and in results written before the metric existed
    time_to_success: float | None = None
    #: harshest deceleration (m/s², >= 0) of a new follower after the ego's lane changes (SUMO env,
    #: ``info["imposed_brake"]``; 0 without a change); None for other envs and in older results
    imposed_brake: float | None = None


@dataclass
class EvalResult:
    """One evaluation: the greedy policy at training step ``step`` over ``episodes``."""

    step: int
    episodes: list[EpisodeResult] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def n(self) -> int:
        return len(self.episodes)

    def rate(self, outcome: str) -> float:
        """Fraction of episodes with ``outcome`` (NaN without episodes)."""
        if not self.episodes:
            return math.nan
        return sum(e.outcome == outcome for e in self.episodes) / len(self.episodes)

    @property
    def success_rate(self) -> float:
        return self.rate("success")

    @property
    def collision_rate(self) -> float:
        """Fraction of episodes that ended in a collision the agent caused."""
        if not self.episodes:
            return math.nan
        return sum(e.outcome == "collision" and e.caused for e in self.episodes) / len(self.episodes)

    @property
    def any_collision_rate(self) -> float:
        return self.rate("collision")

    @property
    def time_limit_rate(self) -> float:
        return self.rate("time_limit")

    @property
    def mean_return(self) -> float:
        return float(np.mean([e.ret for e in self.episodes])) if self.episodes else math.nan

    @property
    def mean_interventions(self) -> float:
        """Mean number of shield interventions per episode (0 without a shield)."""
        return float(np.mean([e.interventions for e in self.episodes])) if self.episodes else math.nan

    @property
    def mean_time_to_success(self) -> float:
        """Mean seconds to success over the episodes that succeeded (NaN without any, or unmeasured)."""
        times = [e.time_to_success for e in self.episodes if e.outcome == "success" and e.time_to_success is not None]
        return float(np.mean(times)) if times else math.nan

    @property
    def mean_imposed_brake(self) -> float:
        """Mean over episodes of each episode's harshest imposed deceleration, m/s² (NaN if unmeasured)."""
        values = [e.imposed_brake for e in self.episodes if e.imposed_brake is not None]
        return float(np.mean(values)) if values else math.nan

    def summary(self) -> dict[str, float]:
        """The row of ``evaluations.csv`` (and the ``eval/*`` metric names)."""
        return {
            "step": float(self.step),
            "episodes": float(self.n),
            "mean_return": self.mean_return,
            "success": self.success_rate,
            "collision": self.collision_rate,
            "any_collision": self.any_collision_rate,
            "time_limit": self.time_limit_rate,
            "mean_length": float(np.mean([e.length for e in self.episodes])) if self.episodes else math.nan,
            "interventions": self.mean_interventions,
            "time_to_success": self.mean_time_to_success,
            "imposed_brake": self.mean_imposed_brake,
            "wall_s": self.wall_s,
        }

    def to_json(self) -> dict[str, Any]:
        return {"step": self.step, "seeds": list(self.seeds), "wall_s": self.wall_s,
                "summary": self.summary(), "episodes": [asdict(e) for e in self.episodes]}  # fmt: skip

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> EvalResult:
        return cls(step=int(data["step"]), episodes=[EpisodeResult(**e) for e in data["episodes"]],
                   seeds=[int(s) for s in data.get("seeds", [])], wall_s=float(data.get("wall_s", 0.0)))  # fmt: skip

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1))
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> EvalResult:
        return cls.from_json(json.loads(Path(path).read_text()))


_CSV_FIELDS = ("step", "episodes", "mean_return", "success", "collision", "any_collision", "time_limit",
               "mean_length", "wall_s")  # fmt: skip


def write_eval_row(path: str | Path, result: EvalResult) -> None:
    """Append one evaluation to ``evaluations.csv`` (header on creation), flushed at once."""
    path = Path(path)
    new = not path.exists() or path.stat().st_size == 0
    row = result.summary()
    with open(path, "a") as fh:
        if new:
            fh.write(",".join(_CSV_FIELDS) + "\n")
        fh.write(",".join(str(int(row[k])) if k in ("step", "episodes") else repr(float(row[k])) for k in _CSV_FIELDS) + "\n")


def read_evaluations(path: str | Path) -> dict[str, np.ndarray]:
    """``evaluations.csv`` as columns (sorted by step; empty arrays if the file is missing)."""
    path = Path(path)
    cols: dict[str, list[float]] = {k: [] for k in _CSV_FIELDS}
    if path.is_file():
        lines = path.read_text().splitlines()
        header = lines[0].split(",") if lines else []
        for line in lines[1:]:
            values = line.split(",")
            if len(values) != len(header):
                continue  # a row cut by a crash
            for k, v in zip(header, values):
                if k in cols:
                    cols[k].append(float(v))
    out = {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}
    order = np.argsort(out["step"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def truncate_evaluations(path: str | Path, before_step: int) -> None:
    """Keep only rows of steps before ``before_step`` (a run resumed at that step redoes the rest)."""
    path = Path(path)
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    if not lines:
        return
    kept = [lines[0]] + [ln for ln in lines[1:] if ln.split(",")[0].isdigit() and int(ln.split(",")[0]) < before_step]
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(kept) + "\n")
    tmp.replace(path)
