"""The training environment in its own process, so the simulation and the gradient step overlap.

``train.env_process`` (default: auto, see :func:`use_env_process`) runs the environment here: the
trainer sends the action, stores (s, a) with the rest of the transition deferred
(``ReplayBuffer.add_deferred``), runs its gradient step while the worker simulates, then takes the
result. On a machine with two cores the step costs about ``max(env step, learner step)`` instead of
their sum. The results are those of the sequential loop, bit for bit: the batch of step t may hold
step t's own transition; when it does (a few percent of the steps: 128 of the thousands stored), the
replay waits for the worker at that gather and the step is not overlapped.

Protocol (one ``multiprocessing`` pipe, pickled tuples): ``("reset", seed)`` -> ``(obs, info)``;
``("step", action)`` -> ``(obs, reward, terminated, truncated, info, reset)`` where ``reset`` is
``(obs, info)`` of the reset that follows a finished episode (done in the worker, before the
answer) or None; ``("pickle",)`` / ``("load", bytes)`` for the runner's checkpoints; ``("close",)``;
``("pool", plan)`` turns the worker into one of :mod:`der_ros.train.env_pool`'s, which choose their own
actions (:mod:`der_ros.train.pool_worker`: its protocol from then on).
An exception in the worker comes back as ``("error", (type name, text))`` and is raised in the
trainer (a ``ConfigError`` as one, anything else as a ``RuntimeError`` with the worker's traceback); a dead
worker is a ``RuntimeError`` naming its exit code. The worker ignores SIGINT (Ctrl-C is the
trainer's to handle: it stops at a step boundary and closes the worker) and exits when the
trainer goes away.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import signal
import time
import traceback
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError
from der_ros.train.envs import make_env_from_config, pickle_env_state
from sumo_bridge import ENV_IDS

__all__ = ["CPUS_PER_RUN_ENV", "MIN_STEPS_FOR_WORKER", "EnvProcess", "cpus_per_run", "use_env_process"]

#: environment variable with the CPUs one training run may use; the suites' backends set it for their
#: runs (the local backend: cores / parallel runs; Ray: the CPUs reserved per task)
CPUS_PER_RUN_ENV = "DER_CPUS_PER_RUN"

#: fewest steps of a run for which auto starts the worker: starting it costs ~0.7-1 s more than opening the
#: env in process, and it saves ~0.3-0.4 ms per ring step on two cores (bench/train_loop.py)
MIN_STEPS_FOR_WORKER = 5000

#: how long a side polls the pipe before it blocks: a blocked reader costs a wake-up on every message
#: (~120 us each way on the 2-core VM of bench/README.md, 236 us per round trip; polled: 90 us)
SPIN_SECONDS = 0.002


def cpus_per_run() -> float:
    """CPUs this training run may use: ``$DER_CPUS_PER_RUN`` if set, else the cores of this process."""
    value = os.environ.get(CPUS_PER_RUN_ENV)
    if value:
        try:
            return float(value)
        except ValueError:
            raise ConfigError(f"${CPUS_PER_RUN_ENV} = {value!r}, expected a number of CPUs") from None
    try:
        return float(len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return float(os.cpu_count() or 1)


def use_env_process(setting: bool | None, env_id: str, evaluator_process: bool = False,
                    total_steps: int = MIN_STEPS_FOR_WORKER) -> bool:
    """``train.env_process``: as set, or (None, auto) for the SUMO environments when the run has a CPU for
    the trainer, one for the env worker and, with periodic evaluations in a process of their own
    (``evaluator_process``), one for those, and the run has at least :data:`MIN_STEPS_FOR_WORKER` steps.
    CartPole's and Atari's steps are shorter than the pipe's round trip: auto keeps them in process. On 2
    cores with ring.yaml's evaluations every 2,500 steps the worker made a whole run slower (63 s against
    53 s: three busy processes on two cores)."""
    if setting is not None:
        return bool(setting)
    return (
        env_id in ENV_IDS
        and total_steps >= MIN_STEPS_FOR_WORKER
        and cpus_per_run() >= 2 + int(evaluator_process)
    )


def _wait(conn: Any, spin: float = SPIN_SECONDS) -> None:
    """Return when ``conn`` has a message: poll for ``spin`` seconds, then block."""
    end = time.perf_counter() + spin
    while not conn.poll():
        if time.perf_counter() > end:
            conn.poll(None)
            return


def _serve(conn: Any, env_cfg: Any, seed: int, spin: float = SPIN_SECONDS) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    env = None
    try:
        try:
            env = make_env_from_config(env_cfg, seed)
            conn.send(("ok", (env.observation_space, env.action_space)))
        except Exception as exc:  # noqa: BLE001 - reported to the trainer
            conn.send(("error", (type(exc).__name__, str(exc))))
            return
        while True:
            try:
                _wait(conn, spin)
                msg = conn.recv()
            except EOFError:  # the trainer is gone
                return
            kind = msg[0]
            try:
                if kind == "step":
                    obs, reward, terminated, truncated, info = env.step(msg[1])
                    reset = env.reset() if terminated or truncated else None
                    conn.send(("ok", (obs, reward, terminated, truncated, info, reset)))
                elif kind == "reset":
                    conn.send(("ok", env.reset(seed=msg[1])))
                elif kind == "pickle":
                    conn.send(("ok", pickle_env_state(env)))
                elif kind == "load":
                    env.close()
                    env = pickle.loads(msg[1])
                    conn.send(("ok", None))
                elif kind == "pool":  # from now on an env pool's worker: it acts by itself until closed
                    from der_ros.train.pool_worker import serve_pool

                    serve_pool(conn, env, msg[1])
                    return
                elif kind == "close":
                    return
                else:
                    conn.send(("error", ("ValueError", f"env process: unknown request {kind!r}")))
            except Exception as exc:  # noqa: BLE001 - reported to the trainer, which raises it
                conn.send(("error", (type(exc).__name__, f"{exc}\n{traceback.format_exc()}")))
    finally:
        if env is not None:
            env.close()
        conn.close()


class EnvProcess:
    """A gymnasium-like handle on an environment in a worker process (``step`` split into
    :meth:`step_async` and :meth:`step_wait`, so the caller works in between)."""

    def __init__(self, env_cfg: Any, seed: int, spin: float = SPIN_SECONDS) -> None:
        """``spin``: seconds each side polls the pipe before it blocks (:data:`SPIN_SECONDS`; 0 = block at
        once, for several workers sharing the cores: :mod:`der_ros.train.env_pool`)."""
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._spin = float(spin)
        self._proc = ctx.Process(target=_serve, args=(child, env_cfg, seed, self._spin), daemon=True, name="der-env")
        self._proc.start()
        child.close()
        self._closed = False
        self._close_sent = False
        self._waiting = False
        try:
            self.observation_space, self.action_space = self._answer()
        except BaseException:
            self.close()
            raise

    def _answer(self) -> Any:
        return self.receive()[1]

    def receive(self) -> tuple[str, Any]:
        """The worker's next message ``(kind, payload)``; an ``("error", ...)`` is raised, as is a dead worker."""
        try:
            _wait(self._conn, self._spin)
            kind, payload = self._conn.recv()
        except (EOFError, ConnectionError):
            raise self._died() from None
        if kind == "error":
            name, text = payload
            if name in ("ConfigError", "ScenarioFileError"):  # a refused config stays a ConfigError (exit 2)
                raise ConfigError(text)
            raise RuntimeError(f"in the environment process: {name}: {text}")
        return kind, payload

    def post(self, *msg: Any) -> None:
        """Send a message that has no answer of its own (an env pool's worker streams its messages)."""
        self._send(msg)

    def _died(self) -> RuntimeError:
        self._proc.join(timeout=5)
        return RuntimeError(f"the environment process died (exit code {self._proc.exitcode})")

    def _send(self, msg: tuple[Any, ...]) -> None:
        try:
            self._conn.send(msg)
        except (BrokenPipeError, ConnectionError):
            raise self._died() from None

    def _call(self, *msg: Any) -> Any:
        if self._waiting:
            raise RuntimeError("env process: step_wait() was not called after step_async()")
        self._send(msg)
        return self._answer()

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        return self._call("reset", seed)

    def step_async(self, action: int) -> None:
        """Start one step; :meth:`step_wait` returns its result."""
        if self._waiting:
            raise RuntimeError("env process: step_async() called twice without step_wait()")
        self._send(("step", action))
        self._waiting = True

    def step_wait(self) -> tuple[np.ndarray, float, bool, bool, dict[str, Any], Any]:
        """(obs, reward, terminated, truncated, info, reset): ``reset`` is the (obs, info) of the next
        episode's reset when this step ended one, else None."""
        if not self._waiting:
            raise RuntimeError("env process: step_wait() without step_async()")
        self._waiting = False
        return self._answer()

    def pickled(self) -> bytes | None:
        """The environment pickled, when the runner would pickle it in process (else None)."""
        return self._call("pickle")

    def load(self, data: bytes) -> None:
        """Replace the worker's environment with an unpickled one (a resumed checkpoint)."""
        self._call("load", data)

    def request_close(self) -> None:
        """Ask the worker to close its env and exit, without waiting (:meth:`close` then waits): several
        workers shut down side by side."""
        if self._closed or self._close_sent:
            return
        self._close_sent = True
        try:
            if self._waiting and self._conn.poll(30):  # a step still out (the trainer failed meanwhile)
                self._conn.recv()
                self._waiting = False
            if self._proc.is_alive():
                self._conn.send(("close",))
        except (BrokenPipeError, EOFError, OSError):
            pass

    def close(self) -> None:
        if self._closed:
            return
        self.request_close()
        self._closed = True
        self._proc.join(timeout=30)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=5)
        self._conn.close()

    @property
    def connection(self) -> Any:
        """The trainer's end of the pipe (for ``multiprocessing.connection.wait`` over several workers)."""
        return self._conn

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def __repr__(self) -> str:
        return f"EnvProcess(pid={self._proc.pid}, alive={self._proc.is_alive()}, parent={os.getpid()})"

