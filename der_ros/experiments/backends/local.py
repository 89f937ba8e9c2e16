"""``--backend local`` (the default): runs in spawned worker processes on this machine.

Spawned, not forked: fresh interpreters, no forked torch/thread state. At most ``jobs`` runs are
handed to the pool at a time, so the backend knows which runs are in progress (the progress
view shows them) and a Ctrl-C never has queued work to cancel inside the pool.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
from collections import deque
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from typing import Any

from der_ros.experiments.backends.base import Backend, EventSink, RunEvent
from der_ros.experiments.suite import RunSpec, default_jobs, run_one
from der_ros.train.env_process import CPUS_PER_RUN_ENV

__all__ = ["LocalBackend"]

log = logging.getLogger(__name__)


def _worker_init(cpus_per_run: float) -> None:
    """Idle workers ignore Ctrl-C (a running training installs its own handler, which stops
    after the current step and writes a checkpoint); one torch thread per worker; the run's share
    of the cores in ``$DER_CPUS_PER_RUN`` (``train.env_process`` auto puts a ring run's env in a
    second process only when the run has two CPUs to itself)."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    os.environ[CPUS_PER_RUN_ENV] = f"{cpus_per_run:g}"


class LocalBackend(Backend):
    """``jobs`` runs at a time (default: the cores available to this process)."""

    name = "local"

    def __init__(self, jobs: int | None = None) -> None:
        if jobs is not None and jobs < 1:
            raise ValueError(f"--jobs {jobs}: expected at least 1")
        self.jobs = jobs

    def _workers(self, n_runs: int) -> int:
        return max(1, min(self.jobs or default_jobs(), max(1, n_runs)))

    def describe(self, n_runs: int) -> str:
        return f"{self._workers(n_runs)} local processes"

    def run(self, specs: Sequence[RunSpec], emit: EventSink) -> list[RunEvent]:
        if not specs:
            return []
        workers = self._workers(len(specs))
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        queue = deque(specs)
        pending: dict[Future[dict[str, Any]], RunSpec] = {}
        outcomes: list[RunEvent] = []
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_worker_init,
                                   initargs=(default_jobs() / workers,))

        def submit() -> None:
            spec = queue.popleft()
            try:
                pending[pool.submit(run_one, spec)] = spec
            except BrokenProcessPool as exc:  # a worker died: the pool takes no more work
                outcomes.append(RunEvent("failed", spec, error=exc))
                emit(outcomes[-1])
                return
            emit(RunEvent("started", spec, where={"host": "local"}))

        try:
            while queue and len(pending) < workers:
                submit()
            while pending:
                finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    spec = pending.pop(fut)
                    try:
                        event = RunEvent("finished", spec, summary=fut.result())
                    except Exception as exc:  # one failed run must not stop the others
                        event = RunEvent("failed", spec, error=exc)
                    outcomes.append(event)
                    emit(event)
                    while queue and len(pending) < workers:
                        submit()
        except KeyboardInterrupt:
            # A terminal's Ctrl-C reaches the workers too, but a SIGINT/SIGTERM sent to this process
            # alone (a background job) would leave them training to the end: pass it on.
            for child in multiprocessing.active_children():
                try:
                    os.kill(child.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
            log.warning("interrupted: workers write checkpoints; rerun the same command to continue")
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return outcomes
