"""Greedy evaluation while training goes on: the evaluators behind the headline numbers.

Training-episode statistics mix in exploration (epsilon-greedy), so they measure the behaviour
policy, not what the agent learned. Every result we publish is therefore the **greedy** policy
(epsilon = 0) run on evaluation seeds that no training run ever uses (:mod:`der_ros.train.eval_seeds`,
docs/evaluation.md); the episodes are run by :func:`der_ros.train.eval_episodes.run_episodes` and
their results are :class:`der_ros.train.eval_result.EvalResult`.

Evaluators run evaluations while training goes on (:func:`make_evaluator`):

* :class:`InlineEvaluator` -- in the training process, with its own environments (gymnasium's
  own envs and Atari: several instances step in lockstep with one batched forward pass);
* :class:`ProcessEvaluator` -- in a second process with its own environment, for envs of which a
  process can hold only one (libsumo). Training only hands over the weights (a few µs) and goes
  on; results are collected at the next poll, and all of them before a checkpoint or the end.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import queue
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import evaluation_seeds

__all__ = [
    "resolve_eval_mode",
    "Evaluator",
    "InlineEvaluator",
    "ProcessEvaluator",
    "make_evaluator",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalSpec:
    """Everything a process needs to rebuild the environment and the Q-network."""

    env_cfg: Any  # der_ros.train.config.EnvConfig
    obs_shape: tuple[int, ...]
    obs_dtype: str
    n_actions: int
    network: str
    hidden_sizes: tuple[int, ...]
    episodes_per_seed: int
    seed_base: int
    parallel_envs: int


def _build_net(spec: EvalSpec, state: dict[str, Any]) -> Any:
    import torch

    from der_ros.agent.networks import make_q_network

    net = make_q_network(spec.obs_shape, np.dtype(spec.obs_dtype), spec.n_actions, spec.network, spec.hidden_sizes)
    net.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in state.items()})
    net.eval()
    return net


def _evaluate(spec: EvalSpec, envs: Sequence[Any], step: int, state: dict[str, Any], episodes: int) -> EvalResult:
    import time

    t0 = time.perf_counter()
    n_streams = math.ceil(episodes / spec.episodes_per_seed) if episodes else 0
    seeds = evaluation_seeds(n_streams, spec.seed_base)
    safety = getattr(spec.env_cfg, "safety", None)
    use_mask = safety is not None and safety.enabled and safety.mode == "mask"
    policy = GreedyQPolicy(_build_net(spec, state), np.dtype(spec.obs_dtype), use_mask=use_mask)
    eps = run_episodes(policy, envs, seeds, episodes, spec.episodes_per_seed)
    return EvalResult(step=step, episodes=eps, seeds=seeds, wall_s=time.perf_counter() - t0)


def _make_envs(spec: EvalSpec, count: int) -> list[Any]:
    return [make_env_from_config(spec.env_cfg, spec.seed_base + i) for i in range(count)]


class Evaluator:
    """Runs greedy evaluations; ``submit`` them, ``poll`` finished ones, ``finish`` waits for all."""

    def submit(self, step: int, state: dict[str, np.ndarray], episodes: int) -> None:
        raise NotImplementedError

    def poll(self) -> list[EvalResult]:
        raise NotImplementedError

    def finish(self) -> list[EvalResult]:
        raise NotImplementedError

    @property
    def pending(self) -> int:
        raise NotImplementedError

    def close(self) -> None:
        pass


class InlineEvaluator(Evaluator):
    """Evaluates at once, in this process, on its own environments (not for libsumo envs)."""

    def __init__(self, spec: EvalSpec) -> None:
        self.spec = spec
        self._envs: list[Any] | None = None
        self._done: list[EvalResult] = []

    def submit(self, step: int, state: dict[str, np.ndarray], episodes: int) -> None:
        if self._envs is None:
            self._envs = _make_envs(self.spec, self.spec.parallel_envs)
        self._done.append(_evaluate(self.spec, self._envs, step, state, episodes))

    def poll(self) -> list[EvalResult]:
        out, self._done = self._done, []
        return out

    def finish(self) -> list[EvalResult]:
        return self.poll()

    @property
    def pending(self) -> int:
        return 0

    def close(self) -> None:
        for env in self._envs or []:
            env.close()
        self._envs = None


def _worker(spec: EvalSpec, jobs: Any, results: Any) -> None:
    """Evaluation process: one environment (libsumo allows one per process), jobs until None.

    ``jobs`` and ``results`` are the reading and the writing end of two pipes."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the trainer decides when to stop
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    parent = os.getppid()
    envs = _make_envs(spec, 1)
    try:
        while True:
            if not jobs.poll(1.0):
                if os.getppid() != parent:  # the trainer died (e.g. SIGKILL): no orphan evaluator
                    break
                continue
            try:
                job = jobs.recv()
            except EOFError:  # the trainer closed its end (or died)
                break
            if job is None:
                break
            step, state, episodes = job
            try:
                results.send(("ok", _evaluate(spec, envs, step, state, episodes).to_json()))
            except Exception as exc:  # noqa: BLE001 - reported to the trainer, which raises it
                results.send(("error", f"evaluation at step {step} failed: {type(exc).__name__}: {exc}"))
    finally:
        for env in envs:
            env.close()


class ProcessEvaluator(Evaluator):
    """Evaluates in a second process (its own environment), while training goes on.

    Jobs and results travel over two pipes, not ``multiprocessing.Queue``: a queue holds named
    semaphores, and when the trainer is SIGKILLed the resource tracker cleans them up with a
    "leaked semaphore objects" warning on the terminal. A feeder thread sends the jobs (a state
    dict can exceed the pipe's buffer: ``submit`` must not wait for the worker to read it).
    """

    def __init__(self, spec: EvalSpec) -> None:
        ctx = mp.get_context("spawn")
        jobs_r, self._jobs = ctx.Pipe(duplex=False)
        self._results, results_w = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_worker, args=(spec, jobs_r, results_w), daemon=True, name="der-eval")
        self._proc.start()
        jobs_r.close()  # the worker's ends: only the worker holds them now (EOF when it dies)
        results_w.close()
        self._outbox: queue.Queue[Any] = queue.Queue()
        self._feeder = threading.Thread(target=self._feed, name="der-eval-feeder", daemon=True)
        self._feeder.start()
        self._pending = 0

    def _feed(self) -> None:
        while True:
            job = self._outbox.get()
            try:
                self._jobs.send(job)
            except OSError:  # the worker is gone; _take reports it
                return
            if job is None:
                return

    def submit(self, step: int, state: dict[str, np.ndarray], episodes: int) -> None:
        self._outbox.put((step, state, episodes))
        self._pending += 1

    def _take(self, block: bool) -> list[EvalResult]:
        out: list[EvalResult] = []
        while self._pending:
            try:
                ready = self._results.poll(1.0 if block else 0)
                message = self._results.recv() if ready else None
            except (EOFError, OSError):
                message, ready = None, False
                if not self._proc.is_alive() or block:
                    self._proc.join(timeout=5)
                    raise RuntimeError(f"the evaluation process died (exit code {self._proc.exitcode})") from None
            if not ready:
                if block and not self._proc.is_alive():
                    raise RuntimeError(f"the evaluation process died (exit code {self._proc.exitcode})") from None
                if block:
                    continue
                break
            kind, payload = message
            self._pending -= 1
            if kind == "error":
                raise RuntimeError(payload)
            out.append(EvalResult.from_json(payload))
        return out

    def poll(self) -> list[EvalResult]:
        return self._take(block=False)

    def finish(self) -> list[EvalResult]:
        return self._take(block=True)

    @property
    def pending(self) -> int:
        return self._pending

    def close(self) -> None:
        if self._proc.is_alive():
            self._outbox.put(None)
            self._feeder.join(timeout=30)
            self._proc.join(timeout=30)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout=5)
        self._jobs.close()
        self._results.close()


def resolve_eval_mode(mode: str, env_id: str) -> str:
    """``train.eval_mode`` with 'auto' resolved: 'process' for the SUMO ids (libsumo: one simulation per
    process), 'inline' otherwise."""
    if mode == "auto":
        return "process" if str(env_id).startswith("der_ros/") else "inline"
    return mode


def make_evaluator(
    env_cfg: Any,
    obs_shape: tuple[int, ...],
    obs_dtype: np.dtype,
    n_actions: int,
    network: str,
    hidden_sizes: Sequence[int],
    episodes_per_seed: int,
    seed_base: int,
    mode: str = "auto",
    parallel_envs: int = 16,
) -> Evaluator:
    """An evaluator for ``env_cfg``: ``mode`` 'process', 'inline', or 'auto' (process for SUMO ids)."""
    mode = resolve_eval_mode(mode, env_cfg.id)
    spec = EvalSpec(env_cfg, tuple(obs_shape), np.dtype(obs_dtype).str, int(n_actions), network,
                    tuple(int(h) for h in hidden_sizes), int(episodes_per_seed), int(seed_base),
                    1 if mode == "process" else int(parallel_envs))  # fmt: skip
    if mode == "process":
        return ProcessEvaluator(spec)
    if mode == "inline":
        return InlineEvaluator(spec)
    raise ValueError(f"eval mode = {mode!r}, expected 'auto', 'process' or 'inline'")
