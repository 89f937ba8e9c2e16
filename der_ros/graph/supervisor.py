"""ROS-free process supervision for ``der graph``: start node processes, watch them, stop them in order.

Why a supervisor of its own: the ROS ``launch`` package is not available from PyPI (see
``docs/architecture.md``), and what ``der graph`` needs is small and must be exact:

* every child gets the same environment (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``,
  one thread for numpy/torch) and its own session, so a terminal Ctrl-C reaches only the runner,
  which then stops the children *in order*;
* stop order matters: the source (bridge) first so no new data appears, then the agent (it saves
  its checkpoint on shutdown), the recorder last so it records everything the others sent;
* each child is stopped with SIGINT, then SIGTERM, then SIGKILL (of its whole session), each after
  a grace period, and is always reaped;
* if a child dies unexpectedly, the others are stopped cleanly and the outcome names the dead
  child, its exit code and the tail of its log.

Pids are written to ``<run_dir>/pids.json`` (name -> pid) so tests and users can find the nodes.
Children get the supervisor's pid in ``DER_ROS_SUPERVISOR_PID``; the node executables use it to
stop (SIGTERM) if the supervisor itself is killed (:mod:`der_ros.nodes.orphans`).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from der_ros.nodes.orphans import SUPERVISOR_PID_ENV

__all__ = [
    "ProcessSpec",
    "ManagedProcess",
    "RunOutcome",
    "Supervisor",
    "DomainLease",
    "reserve_domain_id",
    "ros_environment",
    "ChildFailed",
]

log = logging.getLogger(__name__)

#: Domain ids above ~101 break Fast DDS port arithmetic on Linux; 0 is everybody's default.
DOMAIN_LOW, DOMAIN_HIGH = 1, 101
#: Lock files shared by all users of :func:`reserve_domain_id` (runs, tests, benchmarks): never a shared domain.
_LOCK_DIR = Path(tempfile.gettempdir()) / "der_ros_test_domains"


class DomainLease:
    """A ROS domain id held (lock file) until :meth:`release`; ``fd = -1`` when not locked."""

    def __init__(self, domain_id: int, fd: int = -1) -> None:
        self.domain_id = domain_id
        self._fd = fd

    def release(self) -> None:
        if self._fd >= 0:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = -1


def reserve_domain_id(preferred: int | None = None) -> DomainLease:
    """A domain id in 1..101: ``preferred`` as given (not locked), else a free one derived from the pid."""
    if preferred is not None:
        if not DOMAIN_LOW <= preferred <= 232:
            raise ValueError(f"domain id = {preferred}, expected {DOMAIN_LOW}..232 (<= 101 with Fast DDS)")
        return DomainLease(preferred)
    _LOCK_DIR.mkdir(exist_ok=True)
    span = DOMAIN_HIGH - DOMAIN_LOW + 1
    start = os.getpid() % span
    for i in range(span):
        did = DOMAIN_LOW + (start + i) % span
        fd = os.open(_LOCK_DIR / f"{did}.lock", os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return DomainLease(did, fd)
    raise RuntimeError(f"no free ROS domain id in {DOMAIN_LOW}..{DOMAIN_HIGH}")


def ros_environment(domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for a node process: own domain, localhost-only discovery, unbuffered, 1 thread."""
    env = dict(os.environ if base is None else base)
    env.update(
        {
            "ROS_DOMAIN_ID": str(domain_id),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "PYTHONUNBUFFERED": "1",
            "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
            "OMP_NUM_THREADS": "1",
            "MKL_NUM_THREADS": "1",
        }
    )
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated in Jazzy; the discovery range replaces it
    return env


@dataclass
class ProcessSpec:
    """One child: its name (log file, pid file, messages), command and readiness line."""

    name: str
    argv: list[str]
    env: Mapping[str, str] | None = None
    #: regular expression that appears in the child's output once it is ready (None: ready at start)
    ready_pattern: str | None = None
    ready_timeout: float = 60.0
    #: a zero exit of this child ends the run normally (the source finishing its steps)
    finishes_run: bool = False


class ManagedProcess:
    """A started child with its log file."""

    def __init__(self, spec: ProcessSpec, log_path: Path, cwd: Path | None) -> None:
        self.spec = spec
        self.name = spec.name
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in close()
        env = dict(spec.env if spec.env is not None else os.environ)
        env[SUPERVISOR_PID_ENV] = str(os.getpid())  # the node stops if we die (der_ros.nodes.orphans)
        self.proc = subprocess.Popen(
            spec.argv,
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            cwd=cwd,
        )
        self.started = time.monotonic()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def poll(self) -> int | None:
        return self.proc.poll()

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def tail(self, lines: int = 25) -> str:
        return "\n".join(self.output().splitlines()[-lines:])

    def send(self, sig: int) -> None:
        if self.proc.poll() is None:
            try:
                os.kill(self.proc.pid, sig)
            except ProcessLookupError:
                pass

    def stop(self, grace_int: float, grace_term: float, grace_kill: float = 10.0) -> int:
        """SIGINT, wait; SIGTERM, wait; SIGKILL the session; reap. Returns the exit code."""
        for sig, grace in ((signal.SIGINT, grace_int), (signal.SIGTERM, grace_term)):
            if self.proc.poll() is not None:
                break
            log.debug("sending %s to %s (pid %d)", sig.name, self.name, self.pid)
            self.send(sig)
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop %.0f s after %s", self.name, grace, sig.name)
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait(timeout=grace_kill)
        self.close()
        return int(self.proc.returncode)

    def close(self) -> None:
        if not self._log.closed:
            self._log.close()


@dataclass
class RunOutcome:
    """How a supervised run ended."""

    ok: bool
    reason: str  # "finished", "interrupted", "stopped", or "<name> died (exit <code>)"
    failed: str | None = None
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    tails: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        text = self.reason
        if self.failed is not None and self.tails.get(self.failed):
            text += f"\n--- last lines of {self.failed} ---\n{self.tails[self.failed]}"
        return text


class Supervisor:
    """Starts children in order, watches them, and stops them in a given order.

    Args:
        run_dir: logs go to ``run_dir/logs/<name>.log``, pids to ``run_dir/pids.json``.
        stop_order: names in the order they are stopped; children not listed stop afterwards
            in reverse start order.
        grace_int / grace_term: seconds to wait after SIGINT / SIGTERM.
    """

    def __init__(
        self,
        run_dir: str | Path,
        *,
        stop_order: Sequence[str] = (),
        grace_int: float = 15.0,
        grace_term: float = 5.0,
        cwd: str | Path | None = None,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.log_dir = self.run_dir / "logs"
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.stop_order = list(stop_order)
        self.grace_int = grace_int
        self.grace_term = grace_term
        self.cwd = Path(cwd) if cwd is not None else None
        self.procs: dict[str, ManagedProcess] = {}
        self._stopped: dict[str, int] = {}

    # -- starting ------------------------------------------------------------------------------
    def start(self, spec: ProcessSpec) -> ManagedProcess:
        if spec.name in self.procs:
            raise ValueError(f"a process named {spec.name!r} was already started")
        proc = ManagedProcess(spec, self.log_dir / f"{spec.name}.log", self.cwd)
        self.procs[spec.name] = proc
        self._write_pids()
        log.info("started %s (pid %d): %s", spec.name, proc.pid, " ".join(spec.argv))
        return proc

    def _write_pids(self) -> None:
        tmp = self.run_dir / "pids.json.tmp"
        tmp.write_text(json.dumps({n: p.pid for n, p in self.procs.items()}, indent=1))
        tmp.replace(self.run_dir / "pids.json")

    def wait_ready(self, name: str, timeout: float | None = None) -> None:
        """Block until the child's output matches its ``ready_pattern``.

        Raises :class:`ChildFailed` if it (or any other child) exits first or the time runs out.
        """
        proc = self.procs[name]
        if proc.spec.ready_pattern is None:
            return
        pattern = re.compile(proc.spec.ready_pattern)
        deadline = time.monotonic() + (proc.spec.ready_timeout if timeout is None else timeout)
        while True:
            if pattern.search(proc.output()):
                return
            dead = self.dead_children()
            if dead:
                raise ChildFailed(dead[0], self.procs[dead[0]].poll(), self.procs[dead[0]].tail())
            if time.monotonic() > deadline:
                raise ChildFailed(name, None, proc.tail(), why=f"not ready after {deadline - proc.started:.0f} s")
            time.sleep(0.05)

    def start_all(self, specs: Iterable[ProcessSpec]) -> None:
        """Start each child and wait for it to be ready before starting the next."""
        for spec in specs:
            self.start(spec)
            self.wait_ready(spec.name)

    # -- watching ------------------------------------------------------------------------------
    def dead_children(self) -> list[str]:
        """Children that exited on their own (not stopped by us)."""
        return [n for n, p in self.procs.items() if n not in self._stopped and p.poll() is not None]

    def check(self) -> RunOutcome | None:
        """None while everything runs; an outcome once a child has exited on its own."""
        for name in self.dead_children():
            code = self.procs[name].poll()
            if code == 0 and self.procs[name].spec.finishes_run:
                return RunOutcome(True, "finished")
            return RunOutcome(False, f"{name} died (exit {code})", failed=name)
        return None

    def supervise(
        self,
        *,
        until: Callable[[], bool] | None = None,
        poll_interval: float = 0.2,
        on_tick: Callable[[], None] | None = None,
    ) -> RunOutcome:
        """Watch until a child exits, ``until()`` is true, or Ctrl-C / SIGTERM; then stop everything.

        The returned outcome carries every child's exit code and the log tail of a failed one.
        """
        outcome: RunOutcome | None = None
        old_term = signal.getsignal(signal.SIGTERM)

        def on_term(_signum: int, _frame: object) -> None:
            raise KeyboardInterrupt

        try:
            signal.signal(signal.SIGTERM, on_term)
        except ValueError:  # not in the main thread
            old_term = None
        try:
            while outcome is None:
                outcome = self.check()
                if outcome is None and until is not None and until():
                    outcome = RunOutcome(True, "stopped")
                if outcome is None:
                    if on_tick is not None:
                        on_tick()
                    time.sleep(poll_interval)
        except KeyboardInterrupt:
            outcome = RunOutcome(False, "interrupted")
        finally:
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
        return self.finish(outcome)

    # -- stopping ------------------------------------------------------------------------------
    def order(self) -> list[str]:
        listed = [n for n in self.stop_order if n in self.procs]
        rest = [n for n in reversed(list(self.procs)) if n not in listed]
        return listed + rest

    def stop_all(self) -> dict[str, int]:
        """Stop every running child in :meth:`order`; returns name -> exit code."""
        for name in self.order():
            proc = self.procs[name]
            if name in self._stopped:
                continue
            code = proc.poll()
            if code is None:
                log.info("stopping %s (pid %d)", name, proc.pid)
                code = proc.stop(self.grace_int, self.grace_term)
            else:
                proc.close()
            self._stopped[name] = int(code)
        return dict(self._stopped)

    def finish(self, outcome: RunOutcome) -> RunOutcome:
        """Stop everything (also on a second Ctrl-C during the stop) and fill in codes and tails."""
        try:
            self.stop_all()
        except KeyboardInterrupt:
            for proc in self.procs.values():  # impatient user: no more grace
                if proc.poll() is None:
                    try:
                        os.killpg(proc.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    proc.proc.wait(timeout=10)
            outcome = RunOutcome(False, "interrupted twice: children killed")
        outcome.exit_codes = {n: p.poll() for n, p in self.procs.items()}
        bad_stop = [n for n, c in outcome.exit_codes.items() if c not in (0, None) and n != outcome.failed]
        if outcome.ok and bad_stop:
            # a node that crashed while being stopped (e.g. failed to save) makes the run fail
            name = bad_stop[0]
            outcome = RunOutcome(False, f"{name} exited with {outcome.exit_codes[name]} while stopping",
                                 failed=name, exit_codes=outcome.exit_codes)
        outcome.tails = {n: p.tail() for n, p in self.procs.items()}
        return outcome


class ChildFailed(RuntimeError):
    """A child exited (or never got ready) while the runner was starting the graph."""

    def __init__(self, name: str, code: int | None, tail: str, why: str | None = None) -> None:
        self.name = name
        self.code = code
        self.tail = tail
        super().__init__(f"{name} {why or f'exited with {code}'} during start-up\n--- last lines of {name} ---\n{tail}")
