"""One worker of an env pool (``train.num_envs`` > 1): it chooses its own actions and streams its transitions.

An :class:`~der_ros.train.env_process.EnvProcess` becomes a pool worker on ``("pool", plan)`` (a
:class:`WorkerPlan`: who it is, where it stands, how to act). From then on it steps on its own: its
``k``-th action is epsilon-greedy with the exploration rate of global step ``k * N + j``, its RNG, and the
behaviour snapshot of round ``max(base, k - lag_rounds)`` (the semantics of :mod:`der_ros.train.env_pool`).
It waits only when that snapshot has not come yet (the learner is more than ``lag_rounds`` rounds behind)
or when its next step would lie beyond the run (``k * N + j >= limit``).

Protocol (one pipe, pickled tuples):

* trainer -> worker: ``("snapshot", round, blob)`` a behaviour snapshot (:func:`snapshot_blob`, the same
  bytes for every worker); ``("pause",)``: stop acting and answer ``("state", dict)`` (its pickled env or
  None, observation, step count ``launched``, RNG state); ``("go",)``: act on; ``("close",)``.
* worker -> trainer: ``("result", (obs, action, reward, next_obs, terminated, truncated, info, reset))``
  for each step, in order (``reset``: the (obs, info) of the reset after an episode's end, else None);
  ``("state", dict)``; ``("error", (type name, text))``, after which it acts no more.

A thread reads the pipe, so the trainer never waits to hand over a snapshot while the worker steps (with
a large network and large observations both directions of the pipe could otherwise fill, each side
blocked in a send). torch runs with one thread here.
"""

from __future__ import annotations

import pickle
import queue
import threading
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from der_ros.train.envs import pickle_env_state

__all__ = ["WorkerPlan", "serve_pool", "snapshot_blob", "snapshot_tensors", "blob_of_tensors"]


def snapshot_blob(net: torch.nn.Module) -> bytes:
    """A network's weights as bytes (pickled numpy arrays: cheap to make, exact, no torch needed to read)."""
    return blob_of_tensors(net.state_dict())


def snapshot_tensors(blob: bytes) -> dict[str, torch.Tensor]:
    """The state dict of a :func:`snapshot_blob` (a checkpoint keeps snapshots as tensors)."""
    return {k: torch.from_numpy(v) for k, v in pickle.loads(blob).items()}


def blob_of_tensors(state: dict[str, torch.Tensor]) -> bytes:
    """:func:`snapshot_blob` of a state dict (a snapshot read back from a checkpoint)."""
    return pickle.dumps({k: v.detach().cpu().numpy() for k, v in state.items()}, protocol=5)


@dataclass(frozen=True)
class WorkerPlan:
    """What a pool worker needs to act: sent once, when it starts (or resumes) acting."""

    index: int  #: j, this worker's place in the round robin
    num_envs: int  #: N, the pool's workers
    limit: int  #: the run's transitions in all: the worker takes no step k with k * N + j >= limit
    lag_rounds: int  #: its k-th action uses the snapshot of round max(base, k - lag_rounds)
    base: int  #: the round the run (or a resume without the pool's state) started at
    launched: int  #: k of its next step
    obs: Any  #: what its next action sees
    rng_state: dict[str, Any]  #: its exploration RNG (numpy bit generator state)
    epsilon_schedule: Any  #: ``value(global step)`` -> exploration rate (the learner's schedule)
    n_actions: int
    obs_shape: tuple[int, ...]
    obs_dtype: str  #: numpy dtype of the network's input
    network: str  #: ``agent.network`` ('auto', 'mlp', 'cnn')
    hidden_sizes: tuple[int, ...]  #: ``agent.hidden_sizes``
    snapshots: dict[int, bytes]  #: the snapshots it already needs, by round


class _Actor:
    """The worker's acting state: its step count, observation, RNG, snapshots and behaviour network."""

    def __init__(self, env: Any, plan: WorkerPlan) -> None:
        self.env = env
        self.plan = plan
        self.k = int(plan.launched)
        self.obs = plan.obs
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = plan.rng_state
        self.snapshots = dict(plan.snapshots)
        self.dtype = np.dtype(plan.obs_dtype)
        self.net: torch.nn.Module | None = None
        self.net_round = -1

    def round_for(self, k: int) -> int:
        return max(self.plan.base, k - self.plan.lag_rounds)

    def can_act(self) -> bool:
        p = self.plan
        return self.k * p.num_envs + p.index < p.limit and self.round_for(self.k) in self.snapshots

    def step(self) -> tuple[Any, ...]:
        obs, k = self.obs, self.k
        action = self._act(self.round_for(k), k * self.plan.num_envs + self.plan.index)
        next_obs, reward, terminated, truncated, info = self.env.step(action)
        reset = self.env.reset() if terminated or truncated else None
        self.k += 1
        self.obs = reset[0] if reset is not None else next_obs
        oldest = self.round_for(self.k)
        for r in [r for r in self.snapshots if r < oldest]:
            del self.snapshots[r]
        return obs, action, reward, next_obs, terminated, truncated, info, reset

    def _act(self, r: int, global_step: int) -> int:
        p = self.plan
        eps = p.epsilon_schedule.value(global_step)
        if eps > 0.0 and self.rng.random() < eps:
            return int(self.rng.integers(p.n_actions))
        if self.net is None:
            from der_ros.agent.networks import make_q_network

            self.net = make_q_network(p.obs_shape, self.dtype, p.n_actions, p.network, p.hidden_sizes)
            self.net.requires_grad_(False)
        if self.net_round != r:
            self.net.load_state_dict(snapshot_tensors(self.snapshots[r]))
            self.net_round = r
        with torch.inference_mode():
            x = torch.from_numpy(np.asarray(self.obs, dtype=self.dtype)).unsqueeze(0)
            return int(self.net(x).argmax(1).item())

    def state(self) -> dict[str, Any]:
        return {"env": pickle_env_state(self.env), "obs": np.array(self.obs, copy=True), "launched": self.k,
                "rng": self.rng.bit_generator.state}  # fmt: skip


def _read(conn: Any, inbox: queue.SimpleQueue) -> None:
    """The reader thread: every message into ``inbox`` until ``close`` or the trainer's end (``eof``)."""
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            inbox.put(("eof",))
            return
        inbox.put(msg)
        if msg[0] == "close":
            return


def serve_pool(conn: Any, env: Any, plan: WorkerPlan) -> None:
    """Act, step and stream until ``close`` or the trainer is gone (the caller closes ``env`` and ``conn``)."""
    torch.set_num_threads(1)
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    threading.Thread(target=_read, args=(conn, inbox), daemon=True, name="der-pool-reader").start()
    actor = _Actor(env, plan)
    paused = failed = False
    try:
        while True:
            while True:  # every message that is in; wait for one when there is nothing to do
                idle = paused or failed or not actor.can_act()
                try:
                    msg = inbox.get(block=idle)
                except queue.Empty:
                    break
                kind = msg[0]
                if kind in ("close", "eof"):
                    return
                if kind == "snapshot":
                    actor.snapshots[int(msg[1])] = msg[2]
                elif kind == "pause":
                    paused = True
                    conn.send(("state", actor.state()))
                elif kind == "go":
                    paused = False
                else:
                    failed = True
                    conn.send(("error", ("ValueError", f"env pool worker: unknown request {kind!r}")))
            try:
                result = actor.step()
            except Exception as exc:  # noqa: BLE001 - reported to the trainer, which raises it
                failed = True
                conn.send(("error", (type(exc).__name__, f"{exc}\n{traceback.format_exc()}")))
                continue
            conn.send(("result", result))
    except (BrokenPipeError, ConnectionError, EOFError):  # the trainer is gone
        return
