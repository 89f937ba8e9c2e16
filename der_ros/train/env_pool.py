"""Several environment workers feeding one learner (``train.num_envs`` > 1), deterministically.

Each of the N workers is an :class:`~der_ros.train.env_process.EnvProcess` (one process each: libsumo
allows one simulation per process) turned into a pool worker (:mod:`der_ros.train.pool_worker`). The
learner takes the transitions in a fixed order, round robin -- transition ``g`` of the run is worker
``g % N``'s ``(g // N)``-th step -- and takes one gradient step per transition, as with one env (the same
replay ratio). What a worker does never depends on timing:

* **Acting.** Worker ``j``'s ``k``-th action is epsilon-greedy with the exploration rate of the global step
  that transition will have (``k * N + j``), its own RNG, and a *behaviour snapshot* of the Q-network: the
  network after round ``max(base, k - LAG_ROUNDS)`` (a round = N transitions learnt; ``base`` = 0, or on a
  resume without the pool's state the resume's round). The worker chooses its actions itself, from the
  snapshots the learner sends it at each round's end (the weights pickled once, the same bytes to every
  worker that will use them), and streams its transitions back; it waits for the learner only when it is
  more than :data:`LAG_ROUNDS` rounds ahead (its snapshot has not come) and never steps beyond the run
  (``k * N + j >= train.total_steps``). The lag is what lets N workers overlap at all on this task: a ring
  step that commits a change simulates up to ~45 decisions' worth, 20-30 times a plain step, and in
  lockstep every other worker would wait for it. With N = 1 none of this runs (the loop of
  :mod:`der_ros.train.runner` acts with the current network, as ever).
* **Seeds** (derived from ``train.seed`` = s, see :func:`worker_seed`): worker 0's environment stream is
  seeded with s (as the single env's is), worker j > 0's with ``SeedSequence([s, j])`` folded into the
  training range (below :data:`~der_ros.train.eval_seeds.TRAINING_SEED_LIMIT`, disjoint from the evaluation
  seeds); worker j's exploration RNG is ``default_rng(SeedSequence([s, 7919, j]))``.
* **Waiting.** The trainer blocks on the workers' pipes (``multiprocessing.connection.wait``) only when the
  transition it needs next has not come; the workers block only for a snapshot, a request or the end (no
  polling, ``spin=0``): with N workers and the learner sharing few cores, a spinning reader takes a core a
  simulation needs.

State for an exact resume (:meth:`EnvPool.state_dict`): the pool pauses every worker (:meth:`EnvPool.quiesce`:
each answers, after the transitions it has streamed, with its pickled env when the env pickles, as in
:mod:`der_ros.train.envs`, its current observation, step count and RNG), and saves that with the
transitions simulated but not learnt yet and the behaviour snapshots still needed; then the workers go on,
so a checkpoint changes nothing that follows. :meth:`EnvPool.load_state_dict` hands each worker its state
back. For envs that do not pickle (SUMO, Atari) a resumed run starts fresh episodes, seeded from the step,
as with one env.

A worker that dies or fails raises a ``RuntimeError`` naming the worker (index, pid, exit code), and the
others are closed with the run; Ctrl-C is the trainer's (the workers ignore SIGINT), as with one worker.
"""

from __future__ import annotations

import logging
import pickle
import time
from collections import deque
from multiprocessing.connection import wait
from typing import Any

import numpy as np

from der_ros.train.config import MAX_NUM_ENVS
from der_ros.train.env_process import EnvProcess
from der_ros.train.eval_seeds import TRAINING_SEED_LIMIT, training_env_seed
from der_ros.train.pool_worker import WorkerPlan, blob_of_tensors, snapshot_blob, snapshot_tensors

__all__ = ["EnvPool", "LAG_ROUNDS", "MAX_NUM_ENVS", "worker_seed"]

log = logging.getLogger(__name__)

#: most rounds a worker's behaviour network may lag behind the learner (see the module docstring)
LAG_ROUNDS = 32

#: longest wait for the workers to exit when the pool closes (then they are terminated)
CLOSE_SECONDS = 30.0


def worker_seed(run_seed: int, worker: int) -> int:
    """Environment seed of worker ``worker`` in a run with seed ``run_seed`` (worker 0: the run seed)."""
    if worker == 0:
        return int(run_seed)
    seq = np.random.SeedSequence([int(run_seed), int(worker)])
    return int(seq.generate_state(1, dtype=np.uint64)[0] % TRAINING_SEED_LIMIT)


def _act_rng(run_seed: int, worker: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(run_seed), 7919, int(worker)]))


class _Worker:
    """One env worker and what the pool knows of it."""

    def __init__(self, index: int, proc: EnvProcess) -> None:
        self.index = index
        self.proc = proc
        self.obs: np.ndarray | None = None  # its observation when it last started or paused
        self.received = 0  # its steps whose results the trainer has (its k of the next result to come)
        self.results: deque[tuple[Any, ...]] = deque()  # received, not yet learnt
        self.acting = False  # a pool worker (after start / load_state_dict), streaming its results
        self.paused: dict[str, Any] | None = None  # its answer to a pause


class EnvPool:
    """N env workers, one learner: transitions in a fixed order, the workers act from lagged snapshots."""

    def __init__(self, env_cfg: Any, run_seed: int, num_envs: int) -> None:
        self.n = int(num_envs)
        self.run_seed = int(run_seed)
        self.workers: list[_Worker] = []
        try:
            for j in range(self.n):
                self.workers.append(_Worker(j, EnvProcess(env_cfg, worker_seed(run_seed, j), spin=0.0)))
        except BaseException:
            self.close()
            raise
        self.observation_space = self.workers[0].proc.observation_space
        self.action_space = self.workers[0].proc.action_space
        self.learnt = 0  # transitions the learner has taken (this run, from step 0)
        self.limit = 0  # transitions the run will take in all (no worker steps beyond it)
        self._snapshots: dict[int, bytes] = {}  # the rounds a worker may still use (for checkpoints)
        self._base = 0  # the round this run (or resume) started at: earlier rounds act with its snapshot

    # ------------------------------------------------------------------ set-up
    def start(self, agent: Any, total_steps: int, seeded: bool = True, step: int = 0) -> None:
        """Reset every worker (seeded with :func:`worker_seed`, or on a resume without env state with
        ``training_env_seed(worker_seed, step)``), take the round's snapshot from ``agent`` and set the
        workers acting."""
        self.limit = int(total_steps)
        self.learnt = int(step)
        for w in self.workers:
            seed = worker_seed(self.run_seed, w.index)
            w.obs, _info = self._call(w, w.proc.reset, seed if seeded else training_env_seed(seed, step))
        self._base = self.learnt // self.n
        self._snapshots = {self._base: snapshot_blob(agent.q_net)}
        for w in self.workers:
            w.results = deque()
            self._go(w, agent, self._launched_at(w.index, step), w.obs,
                     _act_rng(self.run_seed, w.index).bit_generator.state)  # fmt: skip

    def _launched_at(self, j: int, step: int) -> int:
        """Steps worker j has had learnt when the learner has taken ``step`` transitions."""
        return (step - j + self.n - 1) // self.n if step > j else 0

    def _go(self, w: _Worker, agent: Any, launched: int, obs: Any, rng_state: dict[str, Any]) -> None:
        """Set ``w`` acting from its ``launched``-th step (``obs``, ``rng_state``)."""
        first = self._round_for(launched)
        plan = WorkerPlan(
            index=w.index, num_envs=self.n, limit=self.limit, lag_rounds=LAG_ROUNDS, base=self._base,
            launched=launched, obs=obs, rng_state=rng_state, epsilon_schedule=agent.epsilon_schedule,
            n_actions=int(agent.n_actions), obs_shape=tuple(agent.obs_shape), obs_dtype=agent.obs_dtype.str,
            network=agent.cfg.network, hidden_sizes=tuple(int(h) for h in agent.cfg.hidden_sizes),
            snapshots={r: b for r, b in self._snapshots.items() if r >= first},
        )  # fmt: skip
        self._call(w, w.proc.post, "pool", plan)
        w.received = launched
        w.acting = True

    def _call(self, w: _Worker, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` on ``w``'s process, a failure named after the worker."""
        try:
            return fn(*args)
        except RuntimeError as exc:
            raise RuntimeError(f"env worker {w.index} of {self.n} (pid {w.proc.pid}): {exc}") from exc

    # ------------------------------------------------------------------ the loop
    def next_transition(self) -> tuple[Any, ...]:
        """The next transition in the fixed order, (obs, action, reward, next_obs, terminated, truncated, info,
        reset) with ``reset`` the (obs, info) of the reset after an episode's end (else None)."""
        w = self.workers[self.learnt % self.n]
        while not w.results:
            self._take(timeout=None)
        return w.results.popleft()

    def learnt_one(self, agent: Any) -> None:
        """The caller has stored the transition and taken its gradient step: count it; at a round's end send
        the round's snapshot to the workers that will act with it."""
        self.learnt += 1
        if self.learnt % self.n:
            return
        r = self.learnt // self.n
        # kept even when no step of this run uses it: a resume with a larger train.total_steps will
        blob = self._snapshots[r] = snapshot_blob(agent.q_net)
        for w in self.workers:
            if (r + LAG_ROUNDS) * self.n + w.index < self.limit:  # its step r + LAG_ROUNDS acts with it
                self._call(w, w.proc.post, "snapshot", r, blob)
        oldest = min(self._round_for(w.received) for w in self.workers)  # no worker acts with an older one
        for old in [k for k in self._snapshots if k < oldest]:
            del self._snapshots[old]
        self._take(timeout=0)  # what has come meanwhile (a worker never waits on a full pipe)

    def _round_for(self, k: int) -> int:
        """The snapshot round a worker's ``k``-th action uses."""
        return max(self._base, k - LAG_ROUNDS)

    def _take(self, timeout: float | None) -> None:
        """Read every message that is in from any acting worker; wait up to ``timeout`` (None: until one is)."""
        conns = {w.proc.connection: w for w in self.workers if w.acting}
        for conn in wait(list(conns), timeout):
            w = conns[conn]
            self._read(w)
            while conn.poll():
                self._read(w)

    def _read(self, w: _Worker) -> None:
        kind, payload = self._call(w, w.proc.receive)
        if kind == "result":
            w.results.append(payload)
            w.received += 1
        elif kind == "state":
            w.paused = payload
        else:  # a bug, not a user error
            raise RuntimeError(f"env pool: unexpected message {kind!r} from worker {w.index}")

    def quiesce(self) -> None:
        """Pause every worker and take its state (after the results it has streamed); :meth:`resume` goes on."""
        for w in self.workers:
            w.paused = None
            self._call(w, w.proc.post, "pause")
        for w in self.workers:
            while w.paused is None:
                self._read(w)
            if int(w.paused["launched"]) != w.received:  # a bug, not a user error
                raise RuntimeError(f"env pool: worker {w.index} paused at step {w.paused['launched']}, "
                                   f"the trainer has {w.received} of its results")  # fmt: skip
            w.obs = w.paused["obs"]

    def resume(self) -> None:
        """The workers act on after :meth:`quiesce` (from where they paused: nothing changes)."""
        for w in self.workers:
            w.paused = None
            self._call(w, w.proc.post, "go")

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        self.quiesce()
        oldest = min(self._round_for(int(w.paused["launched"])) for w in self.workers)  # type: ignore[index]
        state = {
            "num_envs": self.n,
            "learnt": self.learnt,
            "base": self._base,
            "snapshots": {k: snapshot_tensors(b) for k, b in self._snapshots.items() if k >= oldest},
            "workers": [
                {
                    "env": w.paused["env"],  # type: ignore[index]
                    "obs": w.paused["obs"],  # type: ignore[index]
                    "launched": int(w.paused["launched"]),  # type: ignore[index]
                    "rng": w.paused["rng"],  # type: ignore[index]
                    "results": pickle.dumps(list(w.results), protocol=4),
                }
                for w in self.workers
            ],
        }
        self.resume()
        return state

    def load_state_dict(self, state: dict[str, Any], agent: Any, total_steps: int) -> bool:
        """Restore a pool saved by :meth:`state_dict` and set the workers acting; False (nothing restored) when
        an env did not pickle or the checkpoint had another number of workers, in which case the caller starts
        fresh episodes (:meth:`start` with ``seeded=False``)."""
        if int(state["num_envs"]) != self.n:
            log.warning("train.num_envs = %d, the checkpoint's run had %s env workers: starting fresh episodes",
                        self.n, state["num_envs"])  # fmt: skip
            return False
        if any(ws["env"] is None for ws in state["workers"]):
            return False
        self.limit = int(total_steps)
        self.learnt = int(state["learnt"])
        self._base = int(state["base"])
        self._snapshots = {int(k): blob_of_tensors(v) for k, v in state["snapshots"].items()}
        for w, ws in zip(self.workers, state["workers"]):
            self._call(w, w.proc.load, ws["env"])
        for w, ws in zip(self.workers, state["workers"]):
            w.obs = ws["obs"]
            w.results = deque(pickle.loads(ws["results"]))
            self._go(w, agent, int(ws["launched"]), ws["obs"], ws["rng"])
        return True

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Close every worker: all asked at once (each worker's exit, SUMO's and the interpreter's, takes a
        while); what they still stream is read and dropped until they are gone."""
        for w in self.workers:
            w.proc.request_close()
        deadline = time.monotonic() + CLOSE_SECONDS
        for w in self.workers:
            conn = w.proc.connection
            try:
                while conn.poll(max(0.0, deadline - time.monotonic())):
                    conn.recv()
            except (EOFError, OSError):
                pass  # the worker has closed its end: it is exiting
        for w in self.workers:
            w.proc.close()

    @property
    def pids(self) -> list[int | None]:
        return [w.proc.pid for w in self.workers]
