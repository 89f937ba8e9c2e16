"""Live progress of a ``der graph`` run: the counters the monitor collects, and how they are shown.

On a terminal a rich progress bar with a status line under it (log records are routed through
rich so they print above the bar); otherwise a plain status line every 10 s, so logs of
non-interactive runs stay readable.
"""

from __future__ import annotations

import logging
import sys
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
from rich.progress import Progress as RichProgress
from rich.text import Text

from der_ros.contract import EPISODE_ENDS, EPISODE_START

__all__ = ["ProgressSnapshot", "ProgressCounter", "RECENT_RETURNS", "Progress"]

#: episode returns the live counter keeps (the status line shows the mean of the last 10; the final
#: counts and plots of a run come from its bag, see ``graph/run_summary.py``)
RECENT_RETURNS = 1000


@dataclass
class ProgressSnapshot:
    """What the runner shows: counts since the monitor started."""

    steps: int = 0
    episodes: int = 0  # finished episodes
    returns: list[float] = field(default_factory=list)
    outcomes: dict[str, int] = field(default_factory=lambda: dict.fromkeys(EPISODE_ENDS, 0))
    lane_changes: int = 0
    metrics: dict[str, float] = field(default_factory=dict)

    def mean_return(self, window: int = 10) -> float | None:
        tail = self.returns[-window:]
        return sum(tail) / len(tail) if tail else None

    def line(self, window: int = 10) -> str:
        """One-line status text."""
        avg = self.mean_return(window)
        parts = [
            f"episodes {self.episodes}",
            f"return avg({window}) {avg:+.1f}" if avg is not None else "return avg -",
            f"lane changes {self.lane_changes}",
            *(f"{event.replace('_', ' ')} {n}" for event, n in self.outcomes.items()),
        ]
        eps = self.metrics.get("charts/epsilon")
        if eps is not None:
            parts.append(f"eps {eps:.2f}")
        h2 = self.metrics.get("replay/h2_fraction")
        if h2 is not None:
            parts.append(f"H2 frac {h2:.2f}")
        return " | ".join(parts)


class ProgressCounter:
    """The live counts of a run, in memory bounded whatever the run's length (ROS-free).

    Steps, episodes, outcomes and lane changes are counters; only the last :data:`RECENT_RETURNS`
    returns are kept, and the metrics are the latest value per name. (It used to keep every
    episode's event and return: about 1 kB per episode, ~255 kB per 1,000 steps of a ring run,
    issue 45.) Not thread-safe: the monitor holds its lock around every call.
    """

    def __init__(self, recent: int = RECENT_RETURNS) -> None:
        self.steps = 0
        self.episodes = 0
        self.returns: deque[float] = deque(maxlen=recent)
        self.outcomes: dict[str, int] = dict.fromkeys(EPISODE_ENDS, 0)
        self.lane_changes = 0
        self.metrics: dict[str, float] = {}

    def add_step(self) -> None:
        self.steps += 1

    def add_event(self, event: str, values: Mapping[str, Any]) -> None:
        """One ``episode`` event (start events only mark the start: not counted)."""
        if event == EPISODE_START:
            return
        self.episodes += 1
        if event in self.outcomes:
            self.outcomes[event] += 1
        ret = values.get("return")
        if isinstance(ret, (int, float)):
            self.returns.append(float(ret))
        lc = values.get("lane_changes")
        if isinstance(lc, (int, float)):
            self.lane_changes += int(lc)

    def add_metrics(self, metrics: Mapping[str, float]) -> None:
        self.metrics.update(metrics)

    def snapshot(self) -> ProgressSnapshot:
        """A copy (its ``returns`` are the recent ones only)."""
        return ProgressSnapshot(self.steps, self.episodes, list(self.returns), dict(self.outcomes), self.lane_changes,
                                dict(self.metrics))


class Progress:
    """On a terminal: a rich progress bar with a status line under it (log lines go above);
    otherwise a plain status line every 10 s."""

    def __init__(self, total: int) -> None:
        self.total = total
        self._last_line = 0.0
        self._live: Any = None
        self._handlers: list[tuple[logging.Handler, Any]] = []
        if sys.stderr.isatty():
            console = Console(stderr=True)
            self._progress = RichProgress(TextColumn("[bold]decision steps"), BarColumn(), MofNCompleteColumn(),
                                          TimeElapsedColumn(), console=console)
            self._task = self._progress.add_task("graph", total=total)
            self._status = Text("waiting for the first episode", overflow="fold")
            self._live = Live(Group(self._progress, self._status), console=console, refresh_per_second=4)
            root = logging.getLogger()
            for h in list(root.handlers):  # route log records through rich so they print above the bar
                root.removeHandler(h)
                self._handlers.append((h, None))
            self._rich_handler = RichHandler(console=console, show_path=False)
            root.addHandler(self._rich_handler)
            self._live.start()

    def update(self, steps: int, status: str) -> None:
        if self._live is not None:
            self._progress.update(self._task, completed=min(steps, self.total))
            self._status.plain = status
        elif time.monotonic() - self._last_line > 10.0:
            self._last_line = time.monotonic()
            print(f"der graph: step {steps}/{self.total} | {status}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()
            root = logging.getLogger()
            root.removeHandler(self._rich_handler)
            for h, _ in self._handlers:
                root.addHandler(h)
            self._live = None
