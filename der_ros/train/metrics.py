"""Training metrics: ``metrics.csv`` (long format), ``episodes.csv`` and TensorBoard.

Names are stable and namespaced (STYLE.md): ``charts/episodic_return``, ``charts/episodic_length``,
``charts/steps_per_s``, ``charts/epsilon``, ``losses/td_loss``, ``losses/q_values``,
``losses/abs_td_error``, ``replay/h2_fraction``, ``replay/h2_weight_mean``, ...

``metrics.csv`` has one row per (step, name): ``step,wall_time,name,value``, so a metric that
appears later (``replay/h2_size`` once H2 fills) needs no schema change; episode ends add
``charts/episodic_return`` / ``charts/episodic_length`` rows at the step they ended. ``episodes.csv`` has one
row per finished episode: ``episode,step,return,length,wall_time``.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["MetricsWriter", "MeanAccumulator", "read_metrics_csv", "read_episodes_csv", "drop_metric_rows"]

log = logging.getLogger(__name__)

METRICS_HEADER = ["step", "wall_time", "name", "value"]
EPISODES_HEADER = ["episode", "step", "return", "length", "wall_time"]


class MeanAccumulator:
    """Averages each named metric over the gradient steps of one logging interval."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def add(self, metrics: Mapping[str, float]) -> None:
        for k, v in metrics.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(v)
            self.counts[k] = self.counts.get(k, 0) + 1

    def pop_means(self) -> dict[str, float]:
        out = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums.clear()
        self.counts.clear()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"sums": dict(self.sums), "counts": dict(self.counts)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.sums = dict(state["sums"])
        self.counts = dict(state["counts"])


def _truncate_csv(path: Path, step_column: str, max_step: int) -> None:
    """Drop rows logged after ``max_step`` (a resumed run rewrites them)."""
    if not path.is_file():
        return
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
        fieldnames = rows[0].keys() if rows else None
    if fieldnames is None:
        return
    kept = [r for r in rows if int(float(r[step_column])) <= max_step]
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(fieldnames))
        w.writeheader()
        w.writerows(kept)
    tmp.replace(path)


def drop_metric_rows(path: str | Path, step: int, prefix: str) -> None:
    """Remove the ``metrics.csv`` rows of ``step`` whose name starts with ``prefix``.

    A run resumed at a step where it evaluates redoes that evaluation (the checkpoint may follow a
    final evaluation with other settings); its ``eval/*`` rows must not appear twice.
    """
    path = Path(path)
    if not path.is_file():
        return
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return
    kept = [rows[0]] + [r for r in rows[1:] if not (int(float(r[0])) == step and r[2].startswith(prefix))]
    if len(kept) == len(rows):
        return
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerows(kept)
    tmp.replace(path)


class MetricsWriter:
    """Writes scalars to ``metrics.csv``, episodes to ``episodes.csv`` and both to TensorBoard.

    ``resume_step``: when resuming from a checkpoint taken at that step, rows logged after it by
    the interrupted run are dropped first, so the files read like one uninterrupted run.
    """

    def __init__(self, run_dir: str | Path, tensorboard: bool = True, resume_step: int | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.metrics_path = self.run_dir / "metrics.csv"
        self.episodes_path = self.run_dir / "episodes.csv"
        if resume_step is not None:
            _truncate_csv(self.metrics_path, "step", resume_step)
            _truncate_csv(self.episodes_path, "step", resume_step)
        else:
            for p in (self.metrics_path, self.episodes_path):
                if p.exists():
                    p.unlink()
        self._metrics_fh = open(self.metrics_path, "a", newline="")
        self._episodes_fh = open(self.episodes_path, "a", newline="")
        self._metrics = csv.writer(self._metrics_fh)
        self._episodes = csv.writer(self._episodes_fh)
        if self._metrics_fh.tell() == 0:
            self._metrics.writerow(METRICS_HEADER)
        if self._episodes_fh.tell() == 0:
            self._episodes.writerow(EPISODES_HEADER)
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(log_dir=str(self.run_dir / "tb"), purge_step=resume_step)
            except ImportError as exc:  # tensorboard is a dependency; keep the CSVs if it is missing
                log.warning("TensorBoard disabled: %s", exc)

    def scalars(self, step: int, wall_time: float, values: Mapping[str, float]) -> None:
        for name in sorted(values):
            v = float(values[name])
            if math.isnan(v):
                continue
            self._metrics.writerow([step, f"{wall_time:.3f}", name, repr(v)])
            if self._tb is not None:
                self._tb.add_scalar(name, v, step)

    def episode(self, episode: int, step: int, ret: float, length: int, wall_time: float) -> None:
        """One finished episode: a row of episodes.csv, and charts/episodic_{return,length} scalars."""
        self._episodes.writerow([episode, step, repr(float(ret)), int(length), f"{wall_time:.3f}"])
        self.scalars(step, wall_time, {"charts/episodic_return": float(ret), "charts/episodic_length": float(length)})

    def flush(self) -> None:
        self._metrics_fh.flush()
        self._episodes_fh.flush()
        if self._tb is not None:
            self._tb.flush()

    def close(self) -> None:
        self.flush()
        self._metrics_fh.close()
        self._episodes_fh.close()
        if self._tb is not None:
            self._tb.close()


def read_metrics_csv(path: str | Path) -> dict[str, tuple[list[int], list[float]]]:
    """``{name: (steps, values)}`` from a ``metrics.csv``."""
    out: dict[str, tuple[list[int], list[float]]] = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            steps, values = out.setdefault(row["name"], ([], []))
            steps.append(int(row["step"]))
            values.append(float(row["value"]))
    return out


def read_episodes_csv(path: str | Path) -> dict[str, list[float]]:
    """Columns of an ``episodes.csv``: ``{"episode", "step", "return", "length", "wall_time"}``."""
    cols: dict[str, list[float]] = {k: [] for k in EPISODES_HEADER}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            for k in EPISODES_HEADER:
                cols[k].append(float(row[k]))
    return cols
