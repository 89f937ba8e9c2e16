"""One progress view over a whole suite or sweep, for every backend: runs done / running / failed.

On a terminal it is a rich progress bar (one line for the suite, finished runs printed above it);
otherwise (CI, ``nohup``, a log file) plain log lines, one per event that changes the counts.
The ETA assumes every run takes as long as the finished ones did on average (from its own start to
its end) and that as many run at once as ever did so far: the runs still waiting are handed to the
first free slot after the running ones' remaining time. (Elapsed / done x remaining would count
parallel runs as sequential: with 2 slots, the first finished run doubles it.)
"""

from __future__ import annotations

import heapq
import logging
import math
import sys
import time
from collections.abc import Callable
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
                 live: bool | None = None, clock: Callable[[], float] = time.monotonic) -> None:  # fmt: skip
        self.total = total
        self.finished_before = finished_before
        self.done = 0
        self.failed = 0
        self.retried = 0
        self.running: set[str] = set()
        self._clock = clock
        self.t0 = clock()
        self._started: dict[str, float] = {}  # running run -> when it started
        self._durations: list[float] = []  # start to end of every finished run
        self.slots = 0  # the most runs seen running at once
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
        """Seconds left (inf before the first run ends; see the module docstring)."""
        now = self._clock()
        if not self._durations:  # runs ended, none with a start seen: the mean pace so far
            return math.inf if self.done == 0 else (now - self.t0) / self.done * (self.total - self.done)
        mean = sum(self._durations) / len(self._durations)
        free = [max(mean - (now - self._started[key]), 0.0) for key in self.running if key in self._started]
        free += [0.0] * max(self.slots - len(free), 0)
        finish = max(free, default=0.0)
        if not free:
            free = [0.0]
        heapq.heapify(free)
        for _ in range(max(self.total - self.done - len(self.running), 0)):
            end = heapq.heappop(free) + mean
            finish = max(finish, end)
            heapq.heappush(free, end)
        return finish

    def eta_text(self) -> str:
        return "-" if self.done == 0 else format_duration(self.eta_s())

    def __call__(self, event: RunEvent) -> None:
        key = event.spec.run_dir
        line: str | None = None
        if event.kind == "started":
            self.running.add(key)
            self._started[key] = self._clock()
            self.slots = max(self.slots, len(self.running))
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
            self._started.pop(key, None)
            self.retried += 1
            origin = f"from its checkpoint at step {event.step}" if event.step else "from the start"
            line = f"retry {run_label(event.spec)} {origin} (attempt {event.attempt + 1}): {event.error}"
        elif event.kind == "finished":
            self.running.discard(key)
            start = self._started.pop(key, None)
            if start is not None:
                self._durations.append(self._clock() - start)
            self.done += 1
            line = self._finished_line(event)
        elif event.kind == "failed":
            self.running.discard(key)
            self._started.pop(key, None)
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
        wall = self._clock() - self.t0
        log.info("%d runs done in %s (%d failed, %d retried; %d finished before)", self.done,
                 format_duration(wall), self.failed, self.retried, self.finished_before)  # fmt: skip
