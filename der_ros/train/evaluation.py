"""Greedy evaluation on held-out seeds: the headline numbers of every table.

Training-episode statistics mix in exploration (epsilon-greedy), so they measure the behaviour
policy, not what the agent learned. Every result we publish is therefore the **greedy** policy
(epsilon = 0) run on **evaluation seeds** that no training run ever uses (the protocol in the
README, "How we evaluate"):

* Training runs use seeds below :data:`TRAINING_SEED_LIMIT` (run seeds, and the environment seeds
  derived from them, see :func:`training_env_seed`).
* Report evaluations use ``EVAL_SEED_BASE + k``; tuning (any choice of settings, e.g. the
  gap-acceptance rule's thresholds) uses ``TUNING_EVAL_SEED_BASE + k``. The three sets are
  disjoint, and :func:`check_disjoint` asserts it wherever seeds meet.

An evaluation runs ``n`` episodes: ``ceil(n / episodes_per_seed)`` seeded resets, each followed by
``episodes_per_seed - 1`` unseeded ones (the urban network keeps its traffic running between
episodes and a seeded reset costs a 150 s warm-up, so it evaluates in streams of episodes; the
ring and gymnasium's envs use one seed per episode). The result of an evaluation depends only on
the network's weights and the seeds, not on when or in which process it runs.

Evaluators run evaluations while training goes on (:func:`make_evaluator`):

* :class:`InlineEvaluator` -- in the training process, with its own environments (gymnasium's
  own envs and Atari: several instances step in lockstep with one batched forward pass);
* :class:`ProcessEvaluator` -- in a second process with its own environment, for envs of which a
  process can hold only one (libsumo). Training only hands over the weights (a few µs) and goes
  on; results are collected at the next poll, and all of them before a checkpoint or the end.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import os
import queue
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError
from der_ros.train.envs import make_env_from_config

__all__ = [
    "resolve_eval_mode",
    "EVAL_SEED_BASE",
    "TUNING_EVAL_SEED_BASE",
    "TRAINING_SEED_LIMIT",
    "OUTCOMES",
    "EpisodeResult",
    "EvalResult",
    "Policy",
    "GreedyQPolicy",
    "evaluation_seeds",
    "check_training_seed",
    "check_disjoint",
    "training_env_seed",
    "run_episodes",
    "Evaluator",
    "InlineEvaluator",
    "ProcessEvaluator",
    "make_evaluator",
    "net_state",
    "save_policy",
    "load_policy",
    "policy_files",
    "write_eval_row",
    "read_evaluations",
    "truncate_evaluations",
    "EVALUATIONS_CSV",
    "FINAL_EVAL_JSON",
]

log = logging.getLogger(__name__)

#: Training runs and the environment seeds derived from them are below this.
TRAINING_SEED_LIMIT = 1_000_000_000
#: Report evaluation seeds: EVAL_SEED_BASE + k.
EVAL_SEED_BASE = 1_000_000_000
#: Evaluation seeds of tuning runs and of the baselines' tuning: TUNING_EVAL_SEED_BASE + k.
TUNING_EVAL_SEED_BASE = 1_500_000_000
_SEED_SPAN = 500_000_000

#: Episode outcomes: the SUMO env's ``info["event"]``; other envs 'terminated' / 'time_limit'.
OUTCOMES = ("success", "collision", "time_limit", "terminated", "missed")  # missed: a file scenario's exit

EVALUATIONS_CSV = "evaluations.csv"
FINAL_EVAL_JSON = "evaluation.json"


def evaluation_seeds(n: int, base: int = EVAL_SEED_BASE) -> list[int]:
    """The first ``n`` evaluation seeds of the set starting at ``base``."""
    if base not in (EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE):
        raise ConfigError(
            f"eval_seed_base = {base!r}, expected {EVAL_SEED_BASE} (report) or {TUNING_EVAL_SEED_BASE} (tuning)"
        )
    if not 0 <= n <= _SEED_SPAN:
        raise ConfigError(f"evaluation episodes = {n!r}, expected 0..{_SEED_SPAN}")
    return list(range(base, base + n))


def check_training_seed(seed: int, what: str = "train.seed") -> int:
    """``seed`` if it is a valid training seed (below :data:`TRAINING_SEED_LIMIT`), else ConfigError."""
    if not 0 <= int(seed) < TRAINING_SEED_LIMIT:
        raise ConfigError(
            f"{what} = {seed!r}, expected 0 <= seed < {TRAINING_SEED_LIMIT} (seeds from {TRAINING_SEED_LIMIT} on "
            "are reserved for evaluation episodes)"
        )
    return int(seed)


def check_disjoint(training: Iterable[int], evaluation: Iterable[int]) -> None:
    """Raise if any evaluation seed is also a training seed, or lies in the training range."""
    train_set = {int(s) for s in training}
    eval_set = {int(s) for s in evaluation}
    shared = sorted(train_set & eval_set)
    if shared:
        raise ValueError(f"evaluation seeds {shared[:5]} are also training seeds")
    low = [s for s in eval_set if s < TRAINING_SEED_LIMIT]
    if low:
        raise ValueError(f"evaluation seeds {sorted(low)[:5]} lie in the training range (< {TRAINING_SEED_LIMIT})")
    high = [s for s in train_set if s >= TRAINING_SEED_LIMIT]
    if high:
        raise ValueError(f"training seeds {sorted(high)[:5]} lie in the evaluation range (>= {TRAINING_SEED_LIMIT})")


def training_env_seed(run_seed: int, step: int) -> int:
    """Environment seed for a training run restarted at ``step`` (resume): in the training range."""
    seq = np.random.SeedSequence([int(run_seed), int(step)])
    return int(seq.generate_state(1, dtype=np.uint64)[0] % TRAINING_SEED_LIMIT)


# ----------------------------------------------------------------------------- results
@dataclass
class EpisodeResult:
    """One evaluation episode."""

    seed: int | None  # the seed of the reset that began its stream (None: an unseeded follow-up)
    stream: int  # index of the seeded stream it belongs to
    ret: float
    length: int
    outcome: str  # one of OUTCOMES
    caused: bool = False  # a collision the agent caused (SUMO env)
    interventions: int = 0  # commands the safety shield replaced by keep lane (env.safety, docs/safety.md)
    #: seconds from the episode's start to its success (SUMO env, ``info["time_to_success"]``); None when it did
    #: not succeed, and in results written before the metric existed
    time_to_success: float | None = None
    #: harshest deceleration (m/s², >= 0) of a new follower after the ego's lane changes (SUMO env,
    #: ``info["imposed_brake"]``; 0 without a change); None for other envs and in older results
    imposed_brake: float | None = None


@dataclass
class EvalResult:
    """One evaluation: the greedy policy at training step ``step`` over ``episodes``."""

    step: int
    episodes: list[EpisodeResult] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def n(self) -> int:
        return len(self.episodes)

    def rate(self, outcome: str) -> float:
        """Fraction of episodes with ``outcome`` (NaN without episodes)."""
        if not self.episodes:
            return math.nan
        return sum(e.outcome == outcome for e in self.episodes) / len(self.episodes)

    @property
    def success_rate(self) -> float:
        return self.rate("success")

    @property
    def collision_rate(self) -> float:
        """Fraction of episodes that ended in a collision the agent caused."""
        if not self.episodes:
            return math.nan
        return sum(e.outcome == "collision" and e.caused for e in self.episodes) / len(self.episodes)

    @property
    def any_collision_rate(self) -> float:
        return self.rate("collision")

    @property
    def time_limit_rate(self) -> float:
        return self.rate("time_limit")

    @property
    def mean_return(self) -> float:
        return float(np.mean([e.ret for e in self.episodes])) if self.episodes else math.nan

    @property
    def mean_interventions(self) -> float:
        """Mean number of shield interventions per episode (0 without a shield)."""
        return float(np.mean([e.interventions for e in self.episodes])) if self.episodes else math.nan

    @property
    def mean_time_to_success(self) -> float:
        """Mean seconds to success over the episodes that succeeded (NaN without any, or unmeasured)."""
        times = [e.time_to_success for e in self.episodes if e.outcome == "success" and e.time_to_success is not None]
        return float(np.mean(times)) if times else math.nan

    @property
    def mean_imposed_brake(self) -> float:
        """Mean over episodes of each episode's harshest imposed deceleration, m/s² (NaN if unmeasured)."""
        values = [e.imposed_brake for e in self.episodes if e.imposed_brake is not None]
        return float(np.mean(values)) if values else math.nan

    def summary(self) -> dict[str, float]:
        """The row of ``evaluations.csv`` (and the ``eval/*`` metric names)."""
        return {
            "step": float(self.step),
            "episodes": float(self.n),
            "mean_return": self.mean_return,
            "success": self.success_rate,
            "collision": self.collision_rate,
            "any_collision": self.any_collision_rate,
            "time_limit": self.time_limit_rate,
            "mean_length": float(np.mean([e.length for e in self.episodes])) if self.episodes else math.nan,
            "interventions": self.mean_interventions,
            "time_to_success": self.mean_time_to_success,
            "imposed_brake": self.mean_imposed_brake,
            "wall_s": self.wall_s,
        }

    def to_json(self) -> dict[str, Any]:
        return {"step": self.step, "seeds": list(self.seeds), "wall_s": self.wall_s,
                "summary": self.summary(), "episodes": [asdict(e) for e in self.episodes]}  # fmt: skip

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> EvalResult:
        return cls(step=int(data["step"]), episodes=[EpisodeResult(**e) for e in data["episodes"]],
                   seeds=[int(s) for s in data.get("seeds", [])], wall_s=float(data.get("wall_s", 0.0)))  # fmt: skip

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1))
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> EvalResult:
        return cls.from_json(json.loads(Path(path).read_text()))


_CSV_FIELDS = ("step", "episodes", "mean_return", "success", "collision", "any_collision", "time_limit",
               "mean_length", "wall_s")  # fmt: skip


def write_eval_row(path: str | Path, result: EvalResult) -> None:
    """Append one evaluation to ``evaluations.csv`` (header on creation), flushed at once."""
    path = Path(path)
    new = not path.exists() or path.stat().st_size == 0
    row = result.summary()
    with open(path, "a") as fh:
        if new:
            fh.write(",".join(_CSV_FIELDS) + "\n")
        fh.write(",".join(str(int(row[k])) if k in ("step", "episodes") else repr(float(row[k])) for k in _CSV_FIELDS) + "\n")


def read_evaluations(path: str | Path) -> dict[str, np.ndarray]:
    """``evaluations.csv`` as columns (sorted by step; empty arrays if the file is missing)."""
    path = Path(path)
    cols: dict[str, list[float]] = {k: [] for k in _CSV_FIELDS}
    if path.is_file():
        lines = path.read_text().splitlines()
        header = lines[0].split(",") if lines else []
        for line in lines[1:]:
            values = line.split(",")
            if len(values) != len(header):
                continue  # a row cut by a crash
            for k, v in zip(header, values):
                if k in cols:
                    cols[k].append(float(v))
    out = {k: np.asarray(v, dtype=np.float64) for k, v in cols.items()}
    order = np.argsort(out["step"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def truncate_evaluations(path: str | Path, before_step: int) -> None:
    """Keep only rows of steps before ``before_step`` (a run resumed at that step redoes the rest)."""
    path = Path(path)
    if not path.is_file():
        return
    lines = path.read_text().splitlines()
    if not lines:
        return
    kept = [lines[0]] + [ln for ln in lines[1:] if ln.split(",")[0].isdigit() and int(ln.split(",")[0]) < before_step]
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(kept) + "\n")
    tmp.replace(path)


# ----------------------------------------------------------------------------- policies and episodes
#: A batched policy: (observations (B, ...), infos of those B envs) -> B actions.
Policy = Callable[[np.ndarray, Sequence[dict[str, Any]]], Sequence[int]]


class GreedyQPolicy:
    """argmax_a Q(s, a) of a Q-network (epsilon = 0), batched."""

    def __init__(self, net: Any, obs_dtype: np.dtype, use_mask: bool = False) -> None:
        import torch

        self._torch = torch
        self.net = net
        self.obs_dtype = np.dtype(obs_dtype)
        #: a shield in mask mode: argmax over the actions ``info["action_mask"]`` allows
        self.use_mask = use_mask

    def __call__(self, obs: np.ndarray, infos: Sequence[dict[str, Any]]) -> Sequence[int]:
        torch = self._torch
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(obs, dtype=self.obs_dtype))
            q = self.net(x)
            if self.use_mask:
                allowed = torch.from_numpy(np.stack([np.asarray(i["action_mask"], dtype=bool) for i in infos]))
                q = q.masked_fill(~allowed, -math.inf)
            return q.argmax(1).tolist()


def _outcome(info: dict[str, Any], terminated: bool, truncated: bool) -> tuple[str, bool]:
    event = info.get("event")
    if event in OUTCOMES:
        return str(event), bool(info.get("caused", False))
    return ("terminated" if terminated else "time_limit"), False


def _episode_over(env: Any, info: dict[str, Any], terminated: bool, truncated: bool) -> bool:
    """Atari with episodic life: only a game over ends an evaluation episode."""
    if not (terminated or truncated):
        return False
    if "episode" in info or getattr(env.unwrapped, "ale", None) is None:
        return True
    return bool(truncated) or bool(env.unwrapped.ale.game_over())


def run_episodes(
    policy: Policy,
    envs: Sequence[Any],
    seeds: Sequence[int],
    episodes: int,
    episodes_per_seed: int = 1,
) -> list[EpisodeResult]:
    """Run ``episodes`` evaluation episodes of ``policy`` on ``envs`` (stepped in lockstep).

    Stream ``j`` (seed ``seeds[j]``) is a seeded reset followed by ``episodes_per_seed - 1``
    unseeded ones; streams are dealt to the environments in order, so the result does not depend
    on how many environments there are. Results come back in stream order.
    """
    if episodes_per_seed < 1:
        raise ValueError(f"episodes_per_seed = {episodes_per_seed}, expected >= 1")
    n_streams = math.ceil(episodes / episodes_per_seed) if episodes else 0
    if len(seeds) < n_streams:
        raise ValueError(f"{episodes} episodes in streams of {episodes_per_seed} need {n_streams} seeds, got {len(seeds)}")
    sizes = [min(episodes_per_seed, episodes - j * episodes_per_seed) for j in range(n_streams)]
    results: dict[tuple[int, int], EpisodeResult] = {}
    next_stream = 0
    # per env: [stream, episode index in stream, obs, info, return, length] or None when idle
    slots: list[list[Any] | None] = [None] * len(envs)

    def start(i: int, stream: int, k: int) -> None:
        env = envs[i]
        obs, info = env.reset(seed=int(seeds[stream])) if k == 0 else env.reset()
        slots[i] = [stream, k, obs, info, 0.0, 0]

    for i in range(len(envs)):
        if next_stream < n_streams:
            start(i, next_stream, 0)
            next_stream += 1
    while any(s is not None for s in slots):
        active = [i for i, s in enumerate(slots) if s is not None]
        obs = np.stack([slots[i][2] for i in active])  # type: ignore[index]
        actions = policy(obs, [slots[i][3] for i in active])  # type: ignore[index]
        for i, a in zip(active, actions):
            slot = slots[i]
            assert slot is not None
            env = envs[i]
            o, r, terminated, truncated, info = env.step(int(a))
            slot[2], slot[3] = o, info
            slot[4] += float(r)
            slot[5] += 1
            if terminated or truncated:
                if not _episode_over(env, info, terminated, truncated):
                    slot[2], _ = env.reset()  # Atari life lost: the game goes on
                    continue
                stream, k = slot[0], slot[1]
                ret = float(np.asarray(info["episode"]["r"])) if "episode" in info else slot[4]
                outcome, caused = _outcome(info, terminated, truncated)
                tts, brake = info.get("time_to_success"), info.get("imposed_brake")
                results[(stream, k)] = EpisodeResult(
                    seed=int(seeds[stream]) if k == 0 else None, stream=stream, ret=ret, length=int(slot[5]),
                    outcome=outcome, caused=caused, interventions=int(info.get("interventions", 0)),
                    time_to_success=float(tts) if outcome == "success" and tts is not None else None,
                    imposed_brake=None if brake is None else float(brake),
                )  # fmt: skip
                if k + 1 < sizes[stream]:
                    start(i, stream, k + 1)
                elif next_stream < n_streams:
                    start(i, next_stream, 0)
                    next_stream += 1
                else:
                    slots[i] = None
    return [results[key] for key in sorted(results)]


# ----------------------------------------------------------------------------- evaluators
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


def net_state(net: Any) -> dict[str, np.ndarray]:
    """A picklable copy of a network's weights."""
    return {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}


POLICY_PREFIX = "policy_"


def save_policy(directory: str | Path, steps: int, net: Any) -> Path:
    """Write the Q-network's weights at ``steps`` as ``<directory>/policy_<steps>.npz`` (atomic).

    A few tens of kB: the ROS agent node writes one every ``policy_every`` steps so that ``der
    graph`` can evaluate the policy greedily in another process while the graph trains on.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{POLICY_PREFIX}{int(steps):09d}.npz"
    tmp = directory / f".{path.name}.tmp{os.getpid()}.npz"
    np.savez(tmp, **{f"w:{k}": v for k, v in net_state(net).items()}, steps=np.int64(steps))
    os.replace(tmp, path)
    return path


def load_policy(path: str | Path) -> tuple[int, dict[str, np.ndarray]]:
    """(steps, weights) of a file written by :func:`save_policy`."""
    with np.load(Path(path), allow_pickle=False) as data:
        state = {k[2:]: data[k] for k in data.files if k.startswith("w:")}
        return int(data["steps"]), state


def policy_files(directory: str | Path) -> list[Path]:
    """The policy snapshots of ``directory``, by step."""
    directory = Path(directory)
    return sorted(directory.glob(f"{POLICY_PREFIX}*.npz")) if directory.is_dir() else []


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
