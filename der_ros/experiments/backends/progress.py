"""One progress view over a whole suite or sweep, for every backend: runs done / running / failed.

On a terminal it is a rich progress bar (one line for the suite, finished runs printed above it);
otherwise (CI, ``nohup``, a log file) plain log lines, one per event that changes the counts.
The ETA assumes the remaining runs take as long as the finished ones did on average, in parallel
as now: elapsed / done x remaining.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from typing import Any, TextIO

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from der_ros.experiments.backends.base import RunEvent
from der_ros.experiments.suite import RunSpec

__all__ = ["SuiteProgress", "run_label", "format_duration"]

log = logging.getLogger("der_ros.experiments.progress")


def run_label(spec: RunSpec) -> str:
    """``group/method seed k`` (the run's place in the suite)."""
    name = f"{spec.group}/{spec.method.name}" if spec.group else spec.method.name
    return f"{name} seed {spec.seed}"


def format_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class SuiteProgress:
    """Counts runs from :class:`RunEvent` s and shows them; call it with each event."""

    def __init__(self, total: int, finished_before: int = 0, stream: TextIO | None = None,
                 live: bool | None = None) -> None:  # fmt: skip
        self.total = total
        self.finished_before = finished_before
        self.done = 0
        self.failed = 0
        self.retried = 0
        self.running: set[str] = set()
        self.t0 = time.monotonic()
        stream = stream if stream is not None else sys.stderr
        self._progress: Progress | None = None
        if live if live is not None else stream.isatty():
            self._progress = Progress(
                TextColumn("[bold]runs"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[status]}"),
                TimeElapsedColumn(),
                TextColumn("ETA {task.fields[eta]}"),
                console=Console(file=stream),
                transient=False,
            )
            self._task = self._progress.add_task("runs", total=total, status=self.status(), eta=self.eta_text())
            self._progress.start()

    def status(self) -> str:
        text = f"{len(self.running)} running, {self.failed} failed"
        return text + (f", {self.retried} retried" if self.retried else "")

    def eta_s(self) -> float:
        """Seconds left, from the mean pace so far (inf before the first run ends)."""
        if self.done == 0:
            return math.inf
        return (time.monotonic() - self.t0) / self.done * (self.total - self.done)

    def eta_text(self) -> str:
        return "-" if self.done == 0 else format_duration(self.eta_s())

    def __call__(self, event: RunEvent) -> None:
        key = event.spec.run_dir
        line: str | None = None
        if event.kind == "started":
            self.running.add(key)
            where = event.where.get("host") or ""
            if event.where.get("node"):
                where = f"{where} (node {str(event.where['node'])[:8]}, pid {event.where.get('pid')})"
            line = (
                f"start {run_label(event.spec)}"
                + (f" on {where}" if where else "")
                + (f", attempt {event.attempt + 1}" if event.attempt else "")
            )
        elif event.kind == "retry":
            self.running.discard(key)
            self.retried += 1
            origin = f"from its checkpoint at step {event.step}" if event.step else "from the start"
            line = f"retry {run_label(event.spec)} {origin} (attempt {event.attempt + 1}): {event.error}"
        elif event.kind == "finished":
            self.running.discard(key)
            self.done += 1
            line = self._finished_line(event)
        elif event.kind == "failed":
            self.running.discard(key)
            self.done += 1
            self.failed += 1
            line = f"run {event.spec.run_dir} failed: {type(event.error).__name__}: {event.error}"
        if line is None:  # checkpoint events change no count
            return
        counts = f"[{self.done}/{self.total}] {line} | {self.status()}, ETA {self.eta_text()}"
        if self._progress is not None:
            self._progress.update(self._task, completed=self.done, status=self.status(), eta=self.eta_text())
            if event.kind != "started":
                self._progress.console.print(counts, markup=False, highlight=False)
        elif event.kind == "failed":
            log.error(counts)
        else:
            log.info(counts)

    def _finished_line(self, event: RunEvent) -> str:
        s: dict[str, Any] = event.summary or {}
        return (f"{run_label(event.spec)}: {s.get('steps', 0)} steps, {s.get('episodes', 0)} episodes, "
                f"mean return {s.get('mean_return', float('nan')):.2f}"
                + (" (interrupted)" if s.get("interrupted") else ""))  # fmt: skip

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None
        wall = time.monotonic() - self.t0
        log.info("%d runs done in %s (%d failed, %d retried; %d finished before)", self.done,
                 format_duration(wall), self.failed, self.retried, self.finished_before)  # fmt: skip
