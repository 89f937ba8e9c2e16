"""What every backend does: execute a list of runs, report what happens to each as events.

A backend is handed runs that are not finished yet (the caller, :func:`run_specs`, skipped the
others) and must leave each one's files in ``spec.run_dir`` on this machine, exactly as
:func:`der_ros.experiments.suite.run_one` writes them, so that the tables read the same run
directories whichever backend ran them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from der_ros.experiments.suite import RunSpec

__all__ = ["EVENT_KINDS", "RunEvent", "EventSink", "Backend", "BackendError", "RunFailedError"]

#: started: a worker took the run; checkpoint: a periodic checkpoint reached this machine;
#: retry: the run's worker died and the run goes again; finished / failed: the run's final state.
EVENT_KINDS = ("started", "checkpoint", "retry", "finished", "failed")


@dataclass(frozen=True)
class RunEvent:
    """Something that happened to one run; ``attempt`` counts from 0 (retries of a lost worker)."""

    kind: str
    spec: RunSpec
    attempt: int = 0
    summary: dict[str, Any] | None = None
    error: BaseException | None = None
    #: where the attempt runs: pid, node id, host, the worker's own run folder (Ray backend)
    where: dict[str, Any] = field(default_factory=dict)
    #: step of the checkpoint (checkpoint events; retry events: the step the retry resumes from)
    step: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"run event kind {self.kind!r}, expected one of {', '.join(EVENT_KINDS)}")


EventSink = Callable[[RunEvent], None]


class BackendError(RuntimeError):
    """A backend cannot start (missing package, bad flag value); the message names the flag."""

    user_facing = True


class RunFailedError(RuntimeError):
    """A run that failed for good on a backend: its last error, and how many attempts it had."""

    def __init__(self, message: str, attempts: int) -> None:
        super().__init__(message)
        self.attempts = attempts


class Backend(ABC):
    """Executes runs; subclasses: :class:`LocalBackend` (processes), :class:`RayBackend` (tasks)."""

    #: the value of ``--backend``
    name: str = ""

    @abstractmethod
    def describe(self, n_runs: int) -> str:
        """One line for the log: where and how many at once."""

    @abstractmethod
    def run(self, specs: Sequence[RunSpec], emit: EventSink) -> list[RunEvent]:
        """Execute ``specs``; ``emit`` every event as it happens; return each run's final event
        (``finished`` with the summary, or ``failed`` with the error), in any order.

        One failed run must not stop the others. Ctrl-C (KeyboardInterrupt) propagates after the
        runs in progress have saved what they can (a checkpoint), so that a rerun continues.
        """
