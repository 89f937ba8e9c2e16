"""Several environment workers feeding one learner (``train.num_envs`` > 1), deterministically.

Each of the N workers is an :class:`~der_ros.train.env_process.EnvProcess` (one process each: libsumo
allows one simulation per process). The learner takes the transitions in a fixed order, round robin --
transition ``g`` of the run is worker ``g % N``'s ``(g // N)``-th step -- and takes one gradient step per
transition, as with one env (the same replay ratio). What a worker does never depends on timing:

* **Acting.** Worker ``j``'s ``k``-th action is epsilon-greedy with the exploration rate of the global step
  that transition will have (``k * N + j``), its own RNG, and a *behaviour snapshot* of the Q-network: the
  network after round ``max(0, k - LAG_ROUNDS)`` (on a resume without the pool's state: no earlier than the resume's round) (a round = N transitions learnt). So a worker may run up to
  :data:`LAG_ROUNDS` steps ahead of the learner. The lag is what lets N workers overlap at all on this task:
  a ring step that commits a change simulates up to ~45 decisions' worth, 20-30 times a plain step, and in
  lockstep every other worker would wait for it. With N = 1 none of this runs (the loop of
  :mod:`der_ros.train.runner` acts with the current network, as ever).
* **Seeds** (derived from ``train.seed`` = s, see :func:`worker_seed`): worker 0's environment stream is
  seeded with s (as the single env's is), worker j > 0's with ``SeedSequence([s, j])`` folded into the
  training range (below :data:`~der_ros.train.eval_seeds.TRAINING_SEED_LIMIT`, disjoint from the evaluation
  seeds); worker j's exploration RNG is ``default_rng(SeedSequence([s, 7919, j]))``.
* **Waiting.** The trainer blocks on the worker it needs next (``multiprocessing.connection.wait``) and the
  workers block on their pipe (no polling, ``spin=0``): with N workers and the learner sharing few cores,
  a spinning reader takes a core a simulation needs.

State for an exact resume (:meth:`EnvPool.state_dict`): every worker's pickled env (when the env pickles,
as in :mod:`der_ros.train.envs`), its current observation, step count, RNG, the results it has simulated
but the learner has not taken yet, and the behaviour snapshots still needed. Before a checkpoint the pool
waits for the steps in flight (:meth:`EnvPool.quiesce`), which changes nothing that follows. For envs
that do not pickle (SUMO, Atari) a resumed run starts fresh episodes, seeded from the step, as with one env.

A worker that dies or fails raises a ``RuntimeError`` naming the worker (index, pid, exit code), and the
others are closed with the run; Ctrl-C is the trainer's (the workers ignore SIGINT), as with one worker.
"""

from __future__ import annotations

import copy
import logging
import pickle
from collections import deque
from multiprocessing.connection import wait
from typing import Any

import numpy as np
import torch

from der_ros.train.config import MAX_NUM_ENVS
from der_ros.train.env_process import EnvProcess
from der_ros.train.eval_seeds import TRAINING_SEED_LIMIT, training_env_seed

__all__ = ["EnvPool", "LAG_ROUNDS", "MAX_NUM_ENVS", "worker_seed"]

log = logging.getLogger(__name__)

#: most rounds a worker's behaviour network may lag behind the learner (see the module docstring)
LAG_ROUNDS = 32


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

    def __init__(self, index: int, proc: EnvProcess, rng: np.random.Generator) -> None:
        self.index = index
        self.proc = proc
        self.rng = rng
        self.obs: np.ndarray | None = None  # what its next action sees
        self.launched = 0  # steps started (its k)
        self.inflight: tuple[np.ndarray, int] | None = None  # (obs, action) of the step being simulated
        self.results: deque[tuple[Any, ...]] = deque()  # simulated, not yet learnt
        self.net: torch.nn.Module | None = None  # its behaviour network and the round loaded in it
        self.net_round = -1


class EnvPool:
    """N env workers, one learner: transitions in a fixed order, actions from lagged snapshots."""

    def __init__(self, env_cfg: Any, run_seed: int, num_envs: int) -> None:
        self.n = int(num_envs)
        self.run_seed = int(run_seed)
        self.workers: list[_Worker] = []
        try:
            for j in range(self.n):
                self.workers.append(_Worker(j, EnvProcess(env_cfg, worker_seed(run_seed, j), spin=0.0),
                                            _act_rng(run_seed, j)))  # fmt: skip
        except BaseException:
            self.close()
            raise
        self.observation_space = self.workers[0].proc.observation_space
        self.action_space = self.workers[0].proc.action_space
        self.learnt = 0  # transitions the learner has taken (this run, from step 0)
        self.limit = 0  # transitions the run will take in all (no worker steps beyond it)
        self._snapshots: dict[int, dict[str, torch.Tensor]] = {}
        self._base = 0  # the round this run (or resume) started at: earlier rounds act with its snapshot

    # ------------------------------------------------------------------ set-up
    def start(self, agent: Any, total_steps: int, seeded: bool = True, step: int = 0) -> None:
        """Reset every worker (seeded with :func:`worker_seed`, or on a resume without env state with
        ``training_env_seed(worker_seed, step)``) and take the round-0 snapshot from ``agent``."""
        self.limit = int(total_steps)
        self.learnt = int(step)
        for w in self.workers:
            seed = worker_seed(self.run_seed, w.index)
            w.obs, _info = w.proc.reset(seed=seed if seeded else training_env_seed(seed, step))
            w.launched = self._launched_at(w.index, step)
        self._base = self.learnt // self.n
        self._snapshots = {self._base: self._snapshot(agent)}

    def _launched_at(self, j: int, step: int) -> int:
        """Steps worker j has had learnt when the learner has taken ``step`` transitions."""
        return (step - j + self.n - 1) // self.n if step > j else 0

    # ------------------------------------------------------------------ the loop
    def next_transition(self, agent: Any) -> tuple[Any, ...]:
        """The next transition in the fixed order, (obs, action, reward, next_obs, terminated, truncated, info,
        reset) with ``reset`` the (obs, info) of the reset after an episode's end (else None). Starts every
        step that may start (before the caller's gradient step, so the workers simulate meanwhile)."""
        w = self.workers[self.learnt % self.n]
        while not w.results:
            self._launch_ready(agent)
            self._receive(w, agent)
        self._collect_done(agent)
        return w.results.popleft()

    def learnt_one(self, agent: Any) -> None:
        """The caller has stored the transition and taken its gradient step: count it, snapshot at a round's end."""
        self.learnt += 1
        if self.learnt % self.n == 0:
            self._snapshots[self.learnt // self.n] = self._snapshot(agent)
            needed = self._round_for(min(w.launched for w in self.workers))  # the oldest a next action uses
            for old in [k for k in self._snapshots if k < needed]:
                del self._snapshots[old]
        self._collect_done(agent)

    def _collect_done(self, agent: Any) -> None:
        """Take every step that has finished (without waiting) and start the next ones: called around the
        caller's gradient step, so a worker whose step came in meanwhile does not idle until the learner
        next has to wait for a step."""
        flying = {w.proc.connection: w for w in self.workers if w.inflight is not None}
        if flying:
            for conn in wait(list(flying), timeout=0):
                self._collect(flying[conn])
        self._launch_ready(agent)

    def _launch_ready(self, agent: Any) -> None:
        for w in self.workers:
            if w.inflight is not None:
                continue
            k = w.launched
            if k * self.n + w.index >= self.limit:
                continue  # the run ends before this step would be learnt
            r = self._round_for(k)
            if r not in self._snapshots:
                continue  # the learner is more than LAG_ROUNDS rounds behind this worker
            assert w.obs is not None
            action = self._act(agent, w, r, k * self.n + w.index)
            try:
                w.proc.step_async(action)
            except RuntimeError as exc:
                raise RuntimeError(f"env worker {w.index} of {self.n} (pid {w.proc.pid}): {exc}") from exc
            w.inflight = (w.obs, action)
            w.launched += 1

    def _round_for(self, k: int) -> int:
        """The snapshot round a worker's ``k``-th action uses."""
        return max(self._base, k - LAG_ROUNDS)

    def _act(self, agent: Any, w: _Worker, r: int, global_step: int) -> int:
        eps = agent.epsilon_schedule.value(global_step)
        if eps > 0.0 and w.rng.random() < eps:
            return int(w.rng.integers(agent.n_actions))
        if w.net is None:
            w.net = copy.deepcopy(agent.q_net)
            w.net.requires_grad_(False)
        if w.net_round != r:
            w.net.load_state_dict(self._snapshots[r])
            w.net_round = r
        with torch.inference_mode():
            x = torch.from_numpy(np.asarray(w.obs, dtype=agent.obs_dtype)).unsqueeze(0).to(agent.device)
            return int(w.net(x).argmax(1).item())

    def _receive(self, want: _Worker, agent: Any = None) -> None:
        """Block until ``want``'s step is in; a step of another worker that arrives first is taken and (with
        ``agent``) that worker's next step started at once, so it does not idle while the learner waits."""
        if want.inflight is None:
            raise RuntimeError(f"env pool: worker {want.index} has no step to wait for")  # a bug, not a user error
        while want.inflight is not None:
            flying = {w.proc.connection: w for w in self.workers if w.inflight is not None}
            for conn in wait(list(flying)):
                self._collect(flying[conn])
            if agent is not None:
                self._launch_ready(agent)

    def _collect(self, w: _Worker) -> None:
        try:
            next_obs, reward, terminated, truncated, info, reset = w.proc.step_wait()
        except RuntimeError as exc:
            raise RuntimeError(f"env worker {w.index} of {self.n} (pid {w.proc.pid}): {exc}") from exc
        obs, action = w.inflight  # type: ignore[misc]
        w.inflight = None
        w.results.append((obs, action, reward, next_obs, terminated, truncated, info, reset))
        w.obs = reset[0] if (terminated or truncated) else next_obs

    def quiesce(self) -> None:
        """Wait for every step in flight (before a checkpoint); what follows is unchanged."""
        for w in self.workers:
            if w.inflight is not None:
                self._receive(w)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        self.quiesce()
        return {
            "num_envs": self.n,
            "learnt": self.learnt,
            "base": self._base,
            "snapshots": {k: {n: t.clone() for n, t in s.items()} for k, s in self._snapshots.items()},
            "workers": [
                {
                    "env": w.proc.pickled(),
                    "obs": None if w.obs is None else np.array(w.obs, copy=True),
                    "launched": w.launched,
                    "rng": w.rng.bit_generator.state,
                    "results": pickle.dumps(list(w.results), protocol=4),
                }
                for w in self.workers
            ],
        }

    def load_state_dict(self, state: dict[str, Any], agent: Any, total_steps: int) -> bool:
        """Restore a pool saved by :meth:`state_dict`; False (nothing restored) when an env did not pickle or
        the checkpoint had another number of workers, in which case the caller starts fresh episodes (:meth:`start` with ``seeded=False``)."""
        if int(state["num_envs"]) != self.n:
            log.warning("train.num_envs = %d, the checkpoint's run had %s env workers: starting fresh episodes",
                        self.n, state["num_envs"])  # fmt: skip
            return False
        if any(ws["env"] is None for ws in state["workers"]):
            return False
        self.limit = int(total_steps)
        self.learnt = int(state["learnt"])
        self._base = int(state["base"])
        self._snapshots = {int(k): v for k, v in state["snapshots"].items()}
        for w, ws in zip(self.workers, state["workers"]):
            w.proc.load(ws["env"])
            w.obs = ws["obs"]
            w.launched = int(ws["launched"])
            w.rng.bit_generator.state = ws["rng"]
            w.results = deque(pickle.loads(ws["results"]))
        return True

    def _snapshot(self, agent: Any) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in agent.q_net.state_dict().items()}

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        for w in self.workers:  # all at once: each worker's exit (SUMO, the interpreter) takes a while
            w.proc.request_close()
        for w in self.workers:
            w.proc.close()

    @property
    def pids(self) -> list[int | None]:
        return [w.proc.pid for w in self.workers]
