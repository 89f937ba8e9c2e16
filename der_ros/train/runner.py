"""The training loop behind ``der train`` (and each run of the experiment suites).

One learner, :class:`DQNAgent`, driven through its step-wise API; one environment (in this process or
in a worker, :mod:`der_ros.train.env_process`), or ``train.num_envs`` workers feeding it
(:mod:`der_ros.train.env_pool`). Writes a run directory::

    config.yaml     the resolved four-section config (rerun with `der train --config` on it)
    metrics.csv     step,wall_time,name,value (averaged over train.log_interval env steps)
    episodes.csv    episode,step,return,length,wall_time (training episodes, raw returns)
    tb/             TensorBoard event files with the same names
    checkpoint.pt   agent (nets, optimizer, replay, RNGs, counters) + runner state + env state
    summary.json    written when the run ends (finished or interrupted)

Resuming (``resume=<checkpoint>``) restores everything in the checkpoint. The environment is
restored exactly for gymnasium's own pure-Python envs (CartPole, ...), which are pickled into the
checkpoint; for others (Atari, SUMO) the episode in progress is dropped and a fresh one starts,
seeded from the step count.
Ctrl-C (SIGINT) sets a flag that the loop checks after each complete step, so the checkpoint it
writes is always consistent.
"""

from __future__ import annotations

import json
import logging
import math
import pickle
import signal
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

from der_ros.agent.dqn import DQNAgent, resolve_device
from der_ros.safety.apply import replace_unsafe
from der_ros.safety.wrapper import target_mask_for
from der_ros.train.config import ExperimentConfig, save_experiment_config
from der_ros.train.env_pool import EnvPool
from der_ros.train.env_process import EnvProcess, use_env_process
from der_ros.train.envs import make_env_from_config, obs_spec, pickle_env_state
from der_ros.train.eval_policies import net_state
from der_ros.train.eval_result import EVALUATIONS_CSV, FINAL_EVAL_JSON, EvalResult, truncate_evaluations, write_eval_row
from der_ros.train.eval_seeds import check_training_seed, training_env_seed
from der_ros.train.evaluation import Evaluator, make_evaluator, resolve_eval_mode
from der_ros.train.metrics import MeanAccumulator, MetricsWriter, drop_metric_rows
from der_ros.train.resume import ResumePoint, load_resume_point
from der_ros.train.scores import max_moving_average

__all__ = ["RunSummary", "train", "default_run_dir", "replay_label"]

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
SUMMARY_NAME = "summary.json"


@dataclass
class RunSummary:
    """What a finished (or interrupted) run reports; also written as ``summary.json``."""

    run_dir: str
    steps: int
    episodes: int
    interrupted: bool
    wall_time_s: float
    steps_per_s: float
    mean_return: float
    max_ma20_return: float
    checkpoint: str | None
    eval_success: float = math.nan
    eval_collision: float = math.nan
    eval_return: float = math.nan


def replay_label(replay_cfg: Any) -> str:
    """Short method label for directory names: 'uniform', 'per', 'der0.9'."""
    kind = str(getattr(replay_cfg, "kind", "replay"))
    if kind == "der":
        return f"der{getattr(replay_cfg, 'lam', '')}"
    return kind


def default_run_dir(cfg: ExperimentConfig) -> Path:
    """``<runs_root>/<env>-<replay>-<seed>-<UTC timestamp>``."""
    env = cfg.env.id.replace("/", "_")
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    return Path(cfg.train.runs_root) / f"{env}-{replay_label(cfg.replay)}-{cfg.train.seed}-{stamp}"


class _StopFlag:
    """SIGINT or SIGTERM -> stop after the current step and write a checkpoint (a second one raises
    KeyboardInterrupt at once). Installed explicitly for both signals: a run started in the
    background inherits SIGINT ignored, and SIGTERM is how supervisors and ``kill`` stop a job.

    A second signal within :attr:`REPEAT_S` of the first is the same request arriving twice, not
    "again": a terminal's Ctrl-C reaches every process of its group, and a suite's backend then
    forwards the stop to its runs as well (``ray.cancel`` raises SIGINT in the task), which used to
    abort a run while it was writing its interrupted checkpoint. The runner keeps the flag installed
    until that checkpoint and the summary are written."""

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)
    #: seconds after the first signal in which another one does not abort
    REPEAT_S = 2.0

    def __init__(self) -> None:
        self.stop = False
        self._first = 0.0
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.stop:
            if time.monotonic() - self._first >= self.REPEAT_S:
                raise KeyboardInterrupt
            log.warning("%s again within %.0f s: already stopping (once more after that to abort)", name,
                        self.REPEAT_S)
            return
        self.stop = True
        self._first = time.monotonic()
        log.warning("%s: finishing this step, writing a checkpoint (Ctrl-C again to abort)", name)

    def __enter__(self) -> _StopFlag:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handler) for sig in self._SIGNALS}
        return self

    def __exit__(self, *exc: Any) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


class _Progress:
    """A rich progress bar with the last episode return and steps/s; silent when not on a terminal."""

    def __init__(self, total: int, start: int, enabled: bool, description: str) -> None:
        self._progress = None
        if not enabled:
            return
        import sys

        if not sys.stderr.isatty():
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("return {task.fields[ret]}"),
            TextColumn("{task.fields[sps]} steps/s"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            transient=False,
        )
        self._task = self._progress.add_task(description, total=total, completed=start, ret="-", sps="-")
        self._progress.start()

    def update(self, step: int, ret: float | None, sps: float | None) -> None:
        if self._progress is None:
            return
        fields: dict[str, Any] = {}
        if ret is not None:
            fields["ret"] = f"{ret:.1f}"
        if sps is not None:
            fields["sps"] = f"{sps:.0f}"
        self._progress.update(self._task, completed=step, **fields)

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()


class _StepResult:
    """The answer to the step an :class:`EnvProcess` is simulating, fetched once: by the replay when
    a batch first needs the step's transition (:meth:`complete`), else after the gradient step."""

    def __init__(self, env: EnvProcess) -> None:
        self._env = env
        self._result: tuple[Any, ...] | None = None

    def complete(self) -> tuple[float, np.ndarray, bool, bool]:
        """(reward, next_obs, terminated, truncated) for ``ReplayBuffer.add_deferred``."""
        self._result = r = self._env.step_wait()
        return float(r[1]), r[0], bool(r[2]), bool(r[3])

    def take(self) -> tuple[Any, ...]:
        """The step's (obs, reward, terminated, truncated, info, reset); the replay has completed it."""
        r, self._result = self._result, None
        assert r is not None, "the deferred transition was not completed"
        return r


def train(
    cfg: ExperimentConfig,
    run_dir: str | Path | None = None,
    resume: str | Path | None = None,
    on_episode: Callable[[int, int, float], None] | None = None,
    on_checkpoint: Callable[[Path, int], None] | None = None,
) -> RunSummary:
    """Train per ``cfg``; returns a :class:`RunSummary`. ``resume``: a checkpoint written by a run.

    Greedy evaluations (:mod:`der_ros.train.evaluation`) run at step 0, every ``eval_interval``
    steps and at the end, on evaluation seeds no training run uses; they never touch the training
    environment or the agent's RNGs, so a run trains the same with or without them.

    ``on_checkpoint(path, step)`` is called after each periodic checkpoint (``checkpoint_interval``),
    while the run directory is consistent (CSV files flushed up to that step): the Ray backend ships
    the files to its driver then, so a run whose worker dies is retried from there.

    The environment is closed however the run ends (also on an exception): libsumo allows one
    simulation per process, and a reused worker process (Ray's) must be able to run the next run.
    """
    with ExitStack() as cleanup:
        return _TrainingRun(cfg, run_dir, resume, on_episode, on_checkpoint, cleanup).run()


class _TrainingRun:
    """One run of :func:`train`, read top to bottom in :meth:`run`: set up (environment, agent, the
    resumed state, output files), then step (act, simulate, store, learn), log, evaluate and
    checkpoint until ``total_steps`` or a stop, then finish (last checkpoint and evaluation,
    ``summary.json``).

    Every draw of the environment's and the agent's RNGs happens in the order of the loop in
    :meth:`run`, so a resumed run continues exactly where the full run would be
    (``test/train``)."""

    def __init__(
        self,
        cfg: ExperimentConfig,
        run_dir: str | Path | None,
        resume: str | Path | None,
        on_episode: Callable[[int, int, float], None] | None,
        on_checkpoint: Callable[[Path, int], None] | None,
        cleanup: ExitStack,
    ) -> None:
        self.t_cfg = t_cfg = cfg.train  # a node checkpoint replaces agent and replay below, never train
        self.resume = resume
        self.on_episode = on_episode
        self.on_checkpoint = on_checkpoint
        self.cleanup = cleanup
        check_training_seed(t_cfg.seed)
        torch.set_num_threads(t_cfg.threads)
        self.run_path = Path(run_dir or t_cfg.run_dir or default_run_dir(cfg))
        # Everything that can refuse the config (env id, replay memory, batch vs capacity, the checkpoint)
        # runs before the run directory is created: a failed start writes nothing.
        self._open_env(cfg)
        point = self._build_agent(cfg)
        self.run_path.mkdir(parents=True, exist_ok=True)
        save_experiment_config(self.cfg, self.run_path / "config.yaml")
        self.acc = MeanAccumulator()
        self._start_state(point)
        self._open_outputs()

    # ------------------------------------------------------------------------- set-up
    def _open_env(self, cfg: ExperimentConfig) -> None:
        """The training environment: in this process, in a worker, or ``train.num_envs`` workers."""
        t_cfg = self.t_cfg
        self.eval_process = bool(t_cfg.eval_interval) and resolve_eval_mode(t_cfg.eval_mode, cfg.env.id) == "process"
        # (auto decides on the whole run's length, the same when it is resumed)
        in_worker = use_env_process(t_cfg.env_process, cfg.env.id, evaluator_process=self.eval_process,
                                    total_steps=t_cfg.total_steps)  # fmt: skip
        self.pool: EnvPool | None = None
        self.env: Any
        if t_cfg.num_envs > 1:  # N workers, one learner (module env_pool)
            self.env = self.pool = EnvPool(cfg.env, t_cfg.seed, t_cfg.num_envs)
            log.info("environment: %d worker processes feeding the learner (train.num_envs)", t_cfg.num_envs)
        else:
            self.env = EnvProcess(cfg.env, t_cfg.seed) if in_worker else make_env_from_config(cfg.env, t_cfg.seed)
            where = "in a worker process, stepping while the learner updates" if in_worker else "in this process"
            log.info("environment %s (train.env_process = %s)", where,
                     "auto" if t_cfg.env_process is None else t_cfg.env_process)  # fmt: skip
        # the env in use at the end (resuming may replace it), also on a failure
        self.cleanup.callback(lambda: self.env.close())
        self.obs_shape, self.obs_dtype = obs_spec(self.env)
        self.n_actions = int(self.env.action_space.n)

    def _build_agent(self, cfg: ExperimentConfig) -> ResumePoint | None:
        """The learner, restored from ``resume`` if given; returns the resume point (or None)."""
        t_cfg = self.t_cfg
        point: ResumePoint | None = None
        if self.resume:
            point = load_resume_point(self.resume, self.obs_shape, self.n_actions, resolve_device(t_cfg.device))
        if point is not None:
            cfg = point.config(cfg)  # a node checkpoint brings its own agent and replay settings
        self.cfg = cfg
        self.agent = DQNAgent(self.obs_shape, self.obs_dtype, self.n_actions, cfg.agent, cfg.replay, seed=t_cfg.seed,
                              device=t_cfg.device)  # fmt: skip
        if point is not None:
            self.agent.load_state_dict(point.agent_state)
        # mask mode: the next state's mask in the target (refused before any write)
        self.target_mask = target_mask_for(cfg.env)
        return point

    def _start_state(self, point: ResumePoint | None) -> None:
        """The first observation and the runner's counters: fresh, or as the checkpoint left them."""
        t_cfg, agent, pool = self.t_cfg, self.agent, self.pool
        self.episode = 0
        self.last_return: float | None = None
        self.returns: list[float] = []
        self.wall_offset = 0.0
        self.obs: np.ndarray
        self.resume_step: int | None = None
        start_info: dict[str, Any] = {}
        if point is not None and point.runner is not None:
            runner = point.runner
            self.resume_step = agent.steps
            self.episode = int(runner["episode"])
            self.returns = [float(x) for x in runner["returns"]]
            self.last_return = self.returns[-1] if self.returns else None
            self.wall_offset = float(runner["wall_time"])
            self.acc.load_state_dict(runner["accumulator"])
            if pool is not None:
                state = runner.get("pool")
                if state is None or not pool.load_state_dict(state, agent, t_cfg.total_steps):
                    pool.start(agent, t_cfg.total_steps, seeded=False, step=agent.steps)
                self.obs = pool.workers[0].obs
            elif point.env_bytes is not None:
                if isinstance(self.env, EnvProcess):
                    self.env.load(point.env_bytes)
                else:
                    self.env.close()
                    self.env = pickle.loads(point.env_bytes)
                self.obs = np.asarray(runner["obs"])
            else:
                self.obs, start_info = self.env.reset(seed=training_env_seed(t_cfg.seed, agent.steps))
            log.info("resumed from %s at step %d (episode %d)", self.resume, agent.steps, self.episode)
        elif point is not None:  # der graph's agent node: same learner, a new episode in this env
            self.resume_step = agent.steps
            if pool is not None:
                pool.start(agent, t_cfg.total_steps, seeded=False, step=agent.steps)
                self.obs = pool.workers[0].obs
            else:
                self.obs, start_info = self.env.reset(seed=training_env_seed(t_cfg.seed, agent.steps))
            log.info("resumed the agent node's learner from %s at step %d (%d transitions in replay); episode "
                     "counts start at 0", self.resume, agent.steps, len(agent.replay))  # fmt: skip
        elif pool is not None:
            pool.start(agent, t_cfg.total_steps)
            self.obs = pool.workers[0].obs
        else:
            self.obs, start_info = self.env.reset(seed=t_cfg.seed)
        # the shield (env.safety, docs/safety.md): the verdict on ``obs``; the learner stores the applied action
        self.mask: np.ndarray | None = start_info.get("action_mask")
        self.mask_mode = self.cfg.env.safety.enabled and self.cfg.env.safety.mode == "mask"
        agent.target_mask = self.target_mask

    def _open_outputs(self) -> None:
        """Metrics and evaluation files (cut back to the resumed step), the evaluator, the progress bar."""
        t_cfg, cfg, agent, run_path = self.t_cfg, self.cfg, self.agent, self.run_path
        self.redo_eval = (bool(t_cfg.eval_interval) and agent.steps % t_cfg.eval_interval == 0
                          and agent.steps < t_cfg.total_steps)  # fmt: skip
        if self.resume_step is not None and self.redo_eval:  # the evaluation at this step is redone, once
            drop_metric_rows(run_path / "metrics.csv", self.resume_step, "eval/")
        self.writer = MetricsWriter(run_path, tensorboard=t_cfg.tensorboard, resume_step=self.resume_step)
        self.eval_csv = run_path / EVALUATIONS_CSV
        if self.resume_step is not None:
            truncate_evaluations(self.eval_csv, self.resume_step)
        elif self.eval_csv.exists():
            self.eval_csv.unlink()
        self.evaluator: Evaluator | None = None
        if t_cfg.eval_interval or t_cfg.final_eval_episodes:
            self.evaluator = make_evaluator(cfg.env, self.obs_shape, self.obs_dtype, self.n_actions,
                                            cfg.agent.network, cfg.agent.hidden_sizes, t_cfg.eval_episodes_per_seed,
                                            t_cfg.eval_seed_base, mode=t_cfg.eval_mode)  # fmt: skip
        self.last_eval: EvalResult | None = None
        self.progress = _Progress(t_cfg.total_steps, agent.steps, t_cfg.progress,
                                  f"{cfg.env.id} {replay_label(cfg.replay)}")  # fmt: skip
        self.t0 = time.perf_counter()
        self.log_t, self.log_step = self.t0, agent.steps
        self.interrupted = False

    # ------------------------------------------------------------------------- the loop
    def run(self) -> RunSummary:
        """Train until ``total_steps`` (or a stop signal), then finish the run."""
        t_cfg, agent, evaluator = self.t_cfg, self.agent, self.evaluator
        overlap = isinstance(self.env, EnvProcess)
        self.step_result = _StepResult(self.env) if overlap else None
        try:
            # (entered on the cleanup stack: the handlers stay until the interrupted checkpoint and summary are
            # written)
            stop = self.cleanup.enter_context(_StopFlag())
            if self.redo_eval:
                # step 0: the untrained policy, where the curves start; on resume: redo the one at this step
                self._evaluate_now(t_cfg.eval_episodes)
            while agent.steps < t_cfg.total_steps:
                self._step(overlap)
                step = agent.steps
                if step % t_cfg.log_interval == 0:
                    self._log(step)
                if t_cfg.eval_interval and step % t_cfg.eval_interval == 0 and step < t_cfg.total_steps:
                    self._evaluate_now(t_cfg.eval_episodes)
                if t_cfg.checkpoint_interval and step % t_cfg.checkpoint_interval == 0:
                    path = self._checkpoint()
                    if self.on_checkpoint is not None:
                        self.on_checkpoint(path, step)
                if stop.stop:
                    self.interrupted = True
                    break
            if not self.interrupted and evaluator is not None:
                # the final evaluation (more episodes), or the last periodic one if there is none
                self._evaluate_now(t_cfg.final_eval_episodes or (t_cfg.eval_episodes if t_cfg.eval_interval else 0))
                self._record_evaluations(evaluator.finish())
        except BaseException:
            if evaluator is not None:  # no evaluation process outlives a failed run
                evaluator.close()
            raise
        finally:
            self.progress.close()
        return self._finish()

    def _step(self, overlap: bool) -> None:
        """One environment step: act, simulate, store the transition, learn; start a new episode at its end."""
        agent, pool, env = self.agent, self.pool, self.env
        obs = self.obs
        reset: Any = None
        if pool is not None:  # the next transition in the pool's fixed order; the workers simulate meanwhile
            obs, action, reward, next_obs, terminated, truncated, info, reset = pool.next_transition()
            agent.observe(obs, action, float(reward), next_obs, bool(terminated), bool(truncated))
            metrics = agent.learn()
            pool.learnt_one(agent)
        else:
            mask = self.mask
            action = agent.act(obs, mask=mask) if self.mask_mode else agent.act(obs)
            applied, _ = replace_unsafe(action, mask)  # what the shield wrapper will apply (itself if no shield)
            if overlap:  # the gradient step runs while the worker simulates (module env_process)
                step_result = self.step_result
                assert step_result is not None
                env.step_async(action)
                agent.observe_deferred(obs, applied, step_result.complete)
                metrics = agent.learn()  # waits for the step only if its batch holds the step's transition
                agent.replay.resolve_deferred()
                next_obs, reward, terminated, truncated, info, reset = step_result.take()
            else:
                next_obs, reward, terminated, truncated, info = env.step(action)
                agent.observe(obs, applied, float(reward), next_obs, bool(terminated), bool(truncated))
                metrics = agent.learn()
        if metrics:
            self.acc.add(metrics)
        if "episode" in info:
            self._record_episode(info)
        self.mask = info.get("action_mask")
        if terminated or truncated:
            next_obs, reset_info = reset if overlap or pool is not None else env.reset()
            self.mask = reset_info.get("action_mask")
            if "episode" in reset_info:
                self._record_episode(reset_info)
        self.obs = next_obs

    def _log(self, step: int) -> None:
        """Every ``log_interval`` steps: the means of the learner's metrics, rates, replay statistics."""
        now = time.perf_counter()
        sps = (step - self.log_step) / max(now - self.log_t, 1e-9)
        self.log_t, self.log_step = now, step
        values = self.acc.pop_means()
        values["charts/steps_per_s"] = sps
        values["charts/epsilon"] = self.agent.epsilon
        values.update(self.agent.replay.stats())
        self.writer.scalars(step, self._wall(), values)
        self.progress.update(step, self.last_return, sps)
        if self.evaluator is not None:
            self._record_evaluations(self.evaluator.poll())

    # ------------------------------------------------------------------------- records
    def _wall(self) -> float:
        return self.wall_offset + time.perf_counter() - self.t0

    def _record_episode(self, info: dict[str, Any]) -> None:
        ep = info["episode"]
        ret, length = float(np.asarray(ep["r"])), int(np.asarray(ep["l"]))
        self.episode += 1
        self.last_return = ret
        self.returns.append(ret)
        steps, writer = self.agent.steps, self.writer
        writer.episode(self.episode, steps, ret, length, self._wall())
        if "event" in info:  # SUMO lane change: how the episode ended (for Table 3's rates)
            event = info["event"]
            writer.scalars(steps, self._wall(), {"charts/episode_success": float(event == "success"),
                                                 "charts/episode_collision": float(event == "collision")})  # fmt: skip
        if "interventions" in info:  # the shield's vetoes in this episode (env.safety)
            writer.scalars(steps, self._wall(), {"charts/episode_interventions": float(info["interventions"])})
        if self.on_episode is not None:
            self.on_episode(self.episode, steps, ret)

    def _record_evaluations(self, results: list[EvalResult]) -> None:
        for res in sorted(results, key=lambda r: r.step):
            write_eval_row(self.eval_csv, res)
            row = res.summary()
            self.writer.scalars(res.step, self._wall(),
                                {f"eval/{k}": v for k, v in row.items() if k not in ("step", "wall_s")})  # fmt: skip
            self.last_eval = res
            log.debug("evaluation at step %d: %s", res.step, row)

    def _evaluate_now(self, episodes: int) -> None:
        if self.evaluator is not None and episodes > 0:
            self.evaluator.submit(self.agent.steps, net_state(self.agent.q_net), episodes)

    def _checkpoint(self) -> Path:
        if self.evaluator is not None:  # every evaluation up to this step is on disk before the checkpoint
            self._record_evaluations(self.evaluator.finish())
        pool, env = self.pool, self.env
        extra = {
            "runner": {
                "episode": self.episode,
                "returns": self.returns,
                "wall_time": self._wall(),
                "accumulator": self.acc.state_dict(),
                "obs": np.array(self.obs, copy=True),
                **({"pool": pool.state_dict()} if pool is not None else {}),
            },
            "env": None if pool is not None else env.pickled() if isinstance(env, EnvProcess) else pickle_env_state(env),
            "config": self.cfg.to_dict(),
        }
        self.writer.flush()
        return self.agent.save(self.run_path / CHECKPOINT_NAME, extra=extra)

    # ------------------------------------------------------------------------- the end
    def _finish(self) -> RunSummary:
        """The last checkpoint and evaluations, the final ``evaluation.json``, and ``summary.json``."""
        interrupted, evaluator, agent, run_path = self.interrupted, self.evaluator, self.agent, self.run_path
        ckpt_path: Path | None = None
        if interrupted or self.t_cfg.save_final_checkpoint:
            ckpt_path = self._checkpoint()
        if evaluator is not None:
            self._record_evaluations(evaluator.finish())
            evaluator.close()
        last_eval = self.last_eval
        if not interrupted and last_eval is not None and last_eval.step == agent.steps:
            last_eval.save(run_path / FINAL_EVAL_JSON)
        self.writer.close()
        self.env.close()  # before the summary, as ever; closing again at exit is a no-op

        elapsed = self._wall()
        returns = self.returns
        summary = RunSummary(
            run_dir=str(run_path),
            steps=agent.steps,
            episodes=self.episode,
            interrupted=interrupted,
            wall_time_s=elapsed,
            steps_per_s=agent.steps / max(elapsed, 1e-9),
            mean_return=float(np.mean(returns)) if returns else math.nan,
            max_ma20_return=max_moving_average(returns, 20),
            checkpoint=str(ckpt_path) if ckpt_path else None,
            eval_success=last_eval.success_rate if last_eval and not interrupted else math.nan,
            eval_collision=last_eval.collision_rate if last_eval and not interrupted else math.nan,
            eval_return=last_eval.mean_return if last_eval and not interrupted else math.nan,
        )
        tmp = run_path / f".{SUMMARY_NAME}.tmp"
        tmp.write_text(json.dumps(summary.__dict__, indent=2, default=float))
        tmp.replace(run_path / SUMMARY_NAME)
        if interrupted:
            log.warning("interrupted at step %d; resume with --resume %s", agent.steps, ckpt_path)
        return summary
