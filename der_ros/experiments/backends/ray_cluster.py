"""``--backend ray``: every run is one Ray task, on this machine or on a cluster (``--address``).

Why Ray and not our own scheduler (STYLE.md, "prefer the library"): placement by declared
resources (CPU, GPU fractions, custom node resources), workers on other machines, and detection
of dead workers and lost nodes are Ray's; what is ours is what a run needs on top:

* **Artifacts without a shared file system.** The task trains into a temporary folder of its
  worker (:func:`execute_run`) and returns the run's files as bytes
  (:mod:`~der_ros.experiments.backends.artifacts`); the driver writes them to ``spec.run_dir``,
  where the local backend writes. The config is sent resolved (the worker may not have the
  driver's YAML file or working directory); ``summary.json`` is rewritten to name the driver's
  folder, so every file is the one a local run writes.
* **Retries from the last checkpoint.** Ray's own task retry would resubmit the same arguments,
  i.e. start the run over; so Ray retries are off (``max_retries=0``) and the driver resubmits a
  run whose worker died (killed, out of memory, node lost), up to ``--max-retries`` times, with
  the files of its last periodic checkpoint (``train.checkpoint_interval``), which the worker
  sent to the driver through a mailbox (a Ray queue actor on the driver's node) as soon as it was
  written. An exception raised by the run itself (bad config, diverged...) is not retried: it
  would fail again the same way.
* **libsumo's one simulation per process.** Ray reuses worker processes; the runner closes its
  environment however a run ends, so the next run in the same process can open its simulation.
* **Loopback only when local.** A Ray instance started here (no ``--address``) has no dashboard
  and binds every server to 127.0.0.1 (Ray's single-machine mode; by default Ray would bind to
  the machine's network address), and sends no usage statistics.

``import ray`` happens only when this backend starts: ``--backend local`` needs no Ray.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

from der_ros.experiments.backends.artifacts import (
    ARTIFACT_LEVELS,
    RESUME_FILES,
    collect_files,
    relocate_summary,
    write_files,
)
from der_ros.experiments.backends.base import Backend, BackendError, EventSink, RunEvent, RunFailedError
from der_ros.experiments.suite import RunSpec, default_jobs, run_one
from der_ros.train.config import experiment_from_dict
from der_ros.train.env_process import CPUS_PER_RUN_ENV
from der_ros.train.runner import CHECKPOINT_NAME, SUMMARY_NAME

__all__ = ["RayBackend", "RayRunTask", "execute_run", "loopback_ray", "import_ray"]

log = logging.getLogger(__name__)

#: a worker's run folder: <tmp>/der-ray-run-<pid>-<random>
WORKDIR_PREFIX = "der-ray-run-"
#: seconds between two looks at the mailbox while waiting for runs
POLL_S = 0.2
#: after Ctrl-C, how long runs in progress get to return (those that saw the SIGINT stop at once
#: and return their checkpoint); the others are cancelled and resume from their last checkpoint
INTERRUPT_GRACE_S = 15.0


def import_ray() -> Any:
    """The ray module, or one clear line naming the flag when it is not installed."""
    try:
        import ray
    except ImportError as exc:
        raise BackendError(
            f"--backend ray: the ray package is not installed ({exc}); install it with scripts/setup_env.sh "
            "or `pip install -c constraints.txt ray`, or use --backend local"
        ) from None
    return ray


@contextmanager
def loopback_ray() -> Iterator[None]:
    """Within: a Ray instance started in this process binds to 127.0.0.1 and reports no usage.

    Ray's switch for single-machine instances (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, the mode
    it uses on macOS/Windows) makes its node address the loopback address; Ray reads it when it is
    imported, so the constant is set too. Child processes (raylet, GCS, workers) inherit the env.
    """
    import_ray()
    from ray._private import ray_constants

    names = ("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "RAY_USAGE_STATS_ENABLED")
    saved_env = {k: os.environ.get(k) for k in names}
    saved_const = getattr(ray_constants, "ENABLE_RAY_CLUSTER", None)
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        if saved_const is not None:
            ray_constants.ENABLE_RAY_CLUSTER = saved_const


# ----------------------------------------------------------------------------- the task (worker side)
@dataclass(frozen=True)
class RayRunTask:
    """Everything a worker needs for one attempt of one run; nothing refers to the driver's disk."""

    spec: RunSpec
    #: the resolved config (``ExperimentConfig.to_dict()``), built on the driver
    config: dict[str, Any]
    #: files of the driver's run folder to resume from (checkpoint.pt + the CSVs), or none
    resume: dict[str, bytes]
    artifacts: str
    attempt: int
    #: a ``ray.util.queue.Queue`` on the driver's node: ('started' | 'checkpoint', ...) messages
    mailbox: Any


def _send(task: RayRunTask, kind: str, where: dict[str, Any], step: int | None = None,
          files: dict[str, bytes] | None = None) -> None:  # fmt: skip
    """Blocks until the mailbox holds the message: once this returns, a worker death loses nothing."""
    task.mailbox.put((kind, task.spec.run_dir, task.attempt, where, step, files))


def _remove_orphans() -> None:
    """Remove the run folders of workers on this node that died (killed runs leave theirs)."""
    for path in Path(tempfile.gettempdir()).glob(f"{WORKDIR_PREFIX}*-*"):
        pid = path.name[len(WORKDIR_PREFIX) :].split("-", 1)[0]
        if pid.isdigit() and not psutil.pid_exists(int(pid)):
            shutil.rmtree(path, ignore_errors=True)


def execute_run(task: RayRunTask) -> dict[str, Any]:
    """The body of a run's Ray task: train in a private temporary folder, return the files.

    The folder is removed whatever happens; on this worker nothing of the run stays behind (the
    folder of a killed worker is removed by the next run on that node).
    """
    import ray

    _remove_orphans()
    # the CPUs Ray reserved for this task decide train.env_process (auto), not the node's cores
    os.environ[CPUS_PER_RUN_ENV] = f"{ray.get_runtime_context().get_assigned_resources().get('CPU', 1.0):g}"
    workdir = Path(tempfile.mkdtemp(prefix=f"{WORKDIR_PREFIX}{os.getpid()}-"))
    where = {"pid": os.getpid(), "host": socket.gethostname(), "node": ray.get_runtime_context().get_node_id(),
             "workdir": str(workdir)}  # fmt: skip
    run_dir = workdir / "run"
    try:
        write_files(run_dir, task.resume)
        _send(task, "started", where)

        def ship_checkpoint(_path: Path, step: int) -> None:
            if task.artifacts != "small":
                _send(task, "checkpoint", where, step, collect_files(run_dir, task.artifacts, RESUME_FILES))

        cfg = experiment_from_dict(task.config, source=f"{task.spec.config_path} (resolved by the driver)")
        summary = run_one(task.spec, run_dir=run_dir, cfg=cfg, on_checkpoint=ship_checkpoint)
        if summary.get("interrupted"):  # cancelled (Ctrl-C on the driver): its checkpoint goes by mail
            ship_checkpoint(run_dir / CHECKPOINT_NAME, int(summary.get("steps", 0)))
        files = collect_files(run_dir, task.artifacts)
        if SUMMARY_NAME in files:
            files[SUMMARY_NAME] = relocate_summary(files[SUMMARY_NAME], task.spec.run_dir)
        summary = json.loads(relocate_summary(json.dumps(summary, default=float).encode(), task.spec.run_dir))
        return {"summary": summary, "files": files, "where": where}
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


# ----------------------------------------------------------------------------- the driver
class RayBackend(Backend):
    """Runs as Ray tasks; ``address`` (or ``RAY_ADDRESS``) joins a cluster, else a local instance.

    ``num_cpus``: CPUs of a local instance (default: the cores available here). Per run:
    ``cpus_per_run`` CPUs, ``gpus_per_run`` GPUs (default: 1 for runs with ``train.device: cuda``,
    else 0; fractions share a GPU), ``resources`` custom node resources (e.g. ``{"sumo": 1}`` to
    use only nodes started with ``--resources '{"sumo": 8}'``).
    """

    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        num_cpus: int | None = None,
        cpus_per_run: float = 1.0,
        gpus_per_run: float | None = None,
        resources: Mapping[str, float] | None = None,
        max_retries: int = 2,
        artifacts: str = "checkpoint",
    ) -> None:
        if artifacts not in ARTIFACT_LEVELS:
            raise BackendError(f"--artifacts {artifacts!r}: expected one of {', '.join(ARTIFACT_LEVELS)}")
        if max_retries < 0:
            raise BackendError(f"--max-retries {max_retries}: expected 0 or more")
        if cpus_per_run <= 0:
            raise BackendError(f"--cpus-per-run {cpus_per_run}: expected a positive number")
        if gpus_per_run is not None and gpus_per_run < 0:
            raise BackendError(f"--gpus-per-run {gpus_per_run}: expected 0 or more (fractions share a GPU)")
        if num_cpus is not None and num_cpus < 1:
            raise BackendError(f"--jobs {num_cpus}: expected at least 1")
        self.address = address or os.environ.get("RAY_ADDRESS") or None
        self.num_cpus = num_cpus
        self.cpus_per_run = float(cpus_per_run)
        self.gpus_per_run = gpus_per_run
        self.resources = dict(resources or {})
        self.max_retries = int(max_retries)
        self.artifacts = artifacts

    def describe(self, n_runs: int) -> str:
        where = f"the Ray cluster at {self.address}" if self.address else "a local Ray instance (127.0.0.1)"
        return f"Ray tasks on {where}, {self.cpus_per_run:g} CPU per run, up to {self.max_retries} retries per run"

    def run(self, specs: Sequence[RunSpec], emit: EventSink) -> list[RunEvent]:
        if not specs:
            return []
        ray = import_ray()
        if ray.is_initialized():  # the caller's Ray (a test, a notebook): used as it is, left running
            return _Driver(ray, self, specs, emit).run()
        with self._connected(ray):
            return _Driver(ray, self, specs, emit).run()

    @contextmanager
    def _connected(self, ray: Any) -> Iterator[None]:
        """Join the cluster at ``address``, or start a Ray instance on this machine (loopback only,
        ``address="local"``: never one of another user found running here); disconnect at the end."""
        if self.address:
            log.info("connecting to the Ray cluster at %s", self.address)
            ray.init(address=self.address, logging_level=logging.WARNING)
            try:
                yield
            finally:
                ray.shutdown()
            return
        with loopback_ray():
            ray.init(address="local", num_cpus=self.num_cpus or default_jobs(), include_dashboard=False,
                     logging_level=logging.WARNING)  # fmt: skip
            try:
                yield
            finally:
                ray.shutdown()

    def task_options(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """Ray options of one run's task: its resources, and no Ray-side retries (ours resume)."""
        gpus = self.gpus_per_run
        if gpus is None:
            gpus = 1.0 if str(config.get("train", {}).get("device")) == "cuda" else 0.0
        opts: dict[str, Any] = {"num_cpus": self.cpus_per_run, "num_gpus": gpus, "max_retries": 0,
                                "retry_exceptions": False, "name": "der_run"}  # fmt: skip
        if self.resources:
            opts["resources"] = dict(self.resources)
        return opts


class _Driver:
    """One ``RayBackend.run``: submits, waits, writes what arrives, retries lost runs."""

    def __init__(self, ray: Any, backend: RayBackend, specs: Sequence[RunSpec], emit: EventSink) -> None:
        from ray.util.queue import Queue
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        self.ray = ray
        self.backend = backend
        self.specs = {s.run_dir: s for s in specs}
        self.emit = emit
        self.configs = {s.run_dir: s.resolved_config().to_dict() for s in specs}
        self.attempt = {s.run_dir: 0 for s in specs}
        self.checkpoint_step: dict[str, int | None] = {s.run_dir: None for s in specs}
        here = ray.get_runtime_context().get_node_id()
        self.mailbox = Queue(actor_options={"num_cpus": 0,
                                            "scheduling_strategy": NodeAffinitySchedulingStrategy(here, soft=True)})  # fmt: skip
        self.remote = ray.remote(execute_run)
        self.refs: dict[Any, str] = {}
        self.outcomes: list[RunEvent] = []
        #: runs whose current attempt has started; runs that sent a checkpoint (since Ctrl-C)
        self.running: set[str] = set()
        self.saved: set[str] = set()

    def submit(self, key: str) -> None:
        spec = self.specs[key]
        # whatever --artifacts says comes back, a checkpoint on this machine is always resumed from
        resume = collect_files(spec.run_dir, "all" if self.backend.artifacts == "all" else "checkpoint", RESUME_FILES)
        if CHECKPOINT_NAME not in resume:
            resume = {}  # nothing to resume from: the run starts over, as locally
        task = RayRunTask(spec, self.configs[key], resume, self.backend.artifacts, self.attempt[key], self.mailbox)
        ref = self.remote.options(**self.backend.task_options(self.configs[key])).remote(task)
        self.refs[ref] = key

    def drain(self) -> None:
        """Handle the mailbox: 'started' and 'checkpoint' messages of current attempts."""
        from ray.util.queue import Empty

        while True:
            try:
                n = self.mailbox.qsize()
                messages = self.mailbox.get_nowait_batch(n) if n else []
            except Empty:
                messages = []
            if not messages:
                return
            for kind, key, attempt, where, step, files in messages:
                if attempt != self.attempt.get(key):
                    continue  # from an attempt already given up
                spec = self.specs[key]
                if kind == "started":
                    self.running.add(key)
                if kind == "checkpoint":
                    write_files(spec.run_dir, files or {})
                    self.checkpoint_step[key] = step
                    self.saved.add(key)
                self.emit(RunEvent(kind, spec, attempt, where=dict(where), step=step))

    def finish(self, key: str, result: dict[str, Any]) -> None:
        self.running.discard(key)
        spec = self.specs[key]
        write_files(spec.run_dir, result["files"])
        if self.backend.artifacts == "small":
            (Path(spec.run_dir) / CHECKPOINT_NAME).unlink(missing_ok=True)  # an older one would mislead
        event = RunEvent("finished", spec, self.attempt[key], summary=result["summary"], where=result["where"])
        self.outcomes.append(event)
        self.emit(event)

    def lost(self, key: str, exc: BaseException) -> None:
        """The attempt's worker or node is gone: retry from the last checkpoint, or give up."""
        self.drain()  # a checkpoint sent just before the death is used
        self.running.discard(key)
        spec = self.specs[key]
        attempts = self.attempt[key] + 1
        reason = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        if attempts <= self.backend.max_retries:
            self.attempt[key] = attempts
            self.emit(RunEvent("retry", spec, attempts, error=RuntimeError(reason), step=self.checkpoint_step[key]))
            self.submit(key)
            return
        error = RunFailedError(f"{reason} (worker lost {attempts} times; --max-retries {self.backend.max_retries})",
                               attempts)  # fmt: skip
        self.fail(key, error)

    def fail(self, key: str, error: BaseException) -> None:
        self.running.discard(key)
        event = RunEvent("failed", self.specs[key], self.attempt[key], error=error)
        self.outcomes.append(event)
        self.emit(event)

    def collect(self, ref: Any) -> None:
        ray = self.ray
        key = self.refs.pop(ref)
        try:
            result = ray.get(ref)
        except ray.exceptions.RayTaskError as exc:  # raised by the run itself: not retried
            cause = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else exc
            self.drain()
            self.fail(key, cause)
        except ray.exceptions.TaskCancelledError:
            raise KeyboardInterrupt from None
        except ray.exceptions.RayError as exc:  # worker died, node lost, out of memory, object lost
            self.lost(key, exc)
        else:
            self.drain()  # 'started' before 'finished'
            self.finish(key, result)

    def run(self) -> list[RunEvent]:
        ray = self.ray
        try:
            for key in self.specs:
                self.submit(key)
            while self.refs:
                ready, _ = ray.wait(list(self.refs), num_returns=1, timeout=POLL_S)
                self.drain()
                for ref in ready:
                    self.collect(ref)
        except KeyboardInterrupt:
            self.interrupt()
            raise
        finally:
            self.mailbox.shutdown()
        return self.outcomes

    def interrupt(self) -> None:
        """Ctrl-C: ask the runs in progress to stop (Ray's cancel raises the SIGINT the runner
        handles: it stops after the current step and writes a checkpoint, which the task mails to
        this machine), keep what arrives for a moment, then cancel by force; a rerun resumes each
        run from its last checkpoint here."""
        ray = self.ray
        log.warning("interrupted: runs in progress save a checkpoint (up to %.0f s); rerun the same command to "
                    "continue", INTERRUPT_GRACE_S)  # fmt: skip
        self.drain()  # what was sent before Ctrl-C
        waiting = set(self.running) if self.backend.artifacts != "small" else set()
        self.saved.clear()
        for ref in self.refs:
            ray.cancel(ref, force=False)
        deadline = time.monotonic() + INTERRUPT_GRACE_S
        try:
            while (self.refs or waiting - self.saved) and time.monotonic() < deadline:
                ready, _ = ray.wait(list(self.refs), num_returns=1, timeout=POLL_S) if self.refs else ([], [])
                if not self.refs:
                    time.sleep(POLL_S)
                self.drain()
                for ref in ready:
                    key = self.refs.pop(ref)
                    try:
                        self.finish(key, ray.get(ref))
                        waiting.discard(key)
                    except ray.exceptions.RayError:
                        pass
        except KeyboardInterrupt:
            pass
        for ref in self.refs:
            ray.cancel(ref, force=True)
        self.refs.clear()
