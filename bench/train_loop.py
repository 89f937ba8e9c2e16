"""Benchmark: the whole SUMO training loop on the ring, ours vs Stable-Baselines3 (not a test).

In one process, on the default ring scenario (``config/ring.yaml``), one after the other:

* ``env``: the environment alone with a uniformly random policy, resets included at the rate
  the episodes end (``reset_ms_p50``: median time of those resets, the training stream's
  unseeded resets);
* ``learner``: our DQN learner alone, ``observe`` + ``learn`` (one gradient step, DER with
  lambda 0.9, batch 128, the ring MLP 29-256-3) per call, on a DER buffer filled with the
  transitions of the ``env`` run and warmed up until H2 holds promoted transitions;
* ``limit = 1 / (1/env + 1/learner)``: what a loop that did nothing but these two would reach;
* ``loop``: our training loop as ``der train`` runs it, ``der_ros.train.runner.train`` with ring.yaml
  (DER lambda 0.9, one gradient step per decision; CSV metrics on, TensorBoard, progress bar and the
  final checkpoint off) and its default ``train.env_process`` (auto: on a machine with two cores or more
  the environment steps in a worker process while the learner runs its gradient step, with the
  sequential loop's results bit for bit; der_ros/train/env_process.py);
* ``loop_sequential``: the same loop with ``train.env_process: false`` (act, step, observe, learn in
  turn in one process; before 2026-12-02 the default, and what ``loop`` measured then); a checkout
  without the option measures its only loop twice;
* ``loop_eval``: the default loop with the greedy evaluations of config/ring.yaml running beside it
  (``ProcessEvaluator``: at step 0 and every 2,500 steps, 50 episodes each, in a second process with
  its own simulation; the final 300-episode evaluation off); ``train.env_process`` auto then wants a
  third CPU for the env worker, so on two cores this is the sequential loop + the evaluator.
  ``eval_cost = 1 - loop_eval / (the same loop without evaluations)``, both measured between the
  first episode end after learning starts and the last one, is
  what evaluating costs the training steps on this machine (the second process competes for the two
  cores); ``eval_wait_s`` is how much longer train() then waits for evaluations still running;
* ``sb3_loop``: Stable-Baselines3 ``DQN.learn`` on the same environment (same gym id and
  scenario) with the same network (one hidden layer of 256, ReLU), batch 128, buffer 50,000,
  learning_starts, train_freq 1, gradient_steps 1, target update interval, epsilon schedule,
  learning rate, gamma and gradient clipping. SB3's DQN always uses the Huber loss and a
  uniform buffer: it is the peer a user would pick, not a DER implementation.

* ``vec``: our loop with ``train.num_envs: 2`` (two env worker processes feeding the learner, one gradient
  step per decision overall; der_ros/train/env_pool.py) against ``loop`` (N = 1, the default loop on this
  machine), paired within a round: ``vec_speedup``. Both rates are taken from the first episode end after
  learning starts to the last one (starting and closing the worker processes excluded, as SB3's rate
  excludes its ``env.close()``);
* ``sb3_vec``: SB3's DQN on a ``SubprocVecEnv`` of 2 envs against a ``SubprocVecEnv`` of 1, the same
  settings as ``sb3_loop`` but ``gradient_steps=-1`` (one gradient step per env step collected, so the
  replay ratio stays one per decision): ``sb3_vec_speedup``.

Both loops are timed from the step where learning starts to their end (the learning-free
start is excluded for both), by wall clock and by this process's CPU time. ``--repeats`` rounds
run every part once each; rates are the best of the rounds, ratios the median over the rounds
of the ratio within a round (parts of one round run minutes apart at most, so they share the
machine's load better than the best-of figures do).
libsumo allows one simulation per process, so each part closes its environment before the
next opens one. torch runs with one thread. On a shared machine absolute numbers move with the
load; the ratios of one run are what to compare.

    .venv/bin/python bench/train_loop.py            # 4,000 decisions per loop, 3 rounds (~5 min)
    .venv/bin/python bench/train_loop.py --quick    # 1,500 decisions, 1 repeat
    .venv/bin/python bench/train_loop.py --vec-only # only loop, vec, sb3_vec (N = 2 against N = 1)

Only APIs that also existed before the issue-11 changes are used, so the same script measures
an older checkout (run it from that checkout's directory).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

from der_ros.agent.dqn import DQNAgent  # noqa: E402
from der_ros.train.config import ExperimentConfig, TrainConfig, load_experiment_config  # noqa: E402
from der_ros.train.envs import make_env_from_config  # noqa: E402
from der_ros.train.runner import train  # noqa: E402

RING_YAML = Path(__file__).resolve().parent.parent / "config" / "ring.yaml"


def has_env_process() -> bool:
    """Whether this checkout's runner has ``train.env_process`` (older ones: one loop only)."""
    return "env_process" in {f.name for f in dataclasses.fields(TrainConfig)}


def default_loop_uses_worker(evaluate: bool = False) -> bool:
    """Whether ``der train --config config/ring.yaml`` (15,000 steps; evaluations off, or on with
    ``evaluate``) puts the env in a worker process on this machine (``train.env_process`` auto; older
    checkouts: no). The loops here are shorter, so the bench sets the choice explicitly."""
    try:
        from der_ros.train.env_process import use_env_process
    except ImportError:
        return False
    full = load_experiment_config(RING_YAML, {} if evaluate else {"train.eval_interval": 0})
    return use_env_process(full.train.env_process, full.env.id, evaluator_process=evaluate,
                           total_steps=full.train.total_steps)


def has_num_envs() -> bool:
    """Whether this checkout's runner has ``train.num_envs`` (several env workers)."""
    return "num_envs" in {f.name for f in dataclasses.fields(TrainConfig)}


def with_num_envs(cfg: ExperimentConfig, n: int) -> ExperimentConfig:
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, num_envs=n))


def task_settings(cfg: ExperimentConfig) -> dict[str, Any]:
    """What the loops train on (stated in the output, so a number is read against its task)."""
    scenario = dict(cfg.env.kwargs.get("scenario", {}))
    keep = ("step_length", "decision_interval", "max_episode_steps", "commit_on_success", "ring_rebuild_every",
            "settle_time")
    return {
        "env": cfg.env.id,
        "scenario": {k: scenario[k] for k in keep if k in scenario},
        "replay": f"{cfg.replay.kind} lam {cfg.replay.lam}" if cfg.replay.kind == "der" else cfg.replay.kind,
        "batch_size": cfg.agent.batch_size,
        "hidden_sizes": list(cfg.agent.hidden_sizes),
        "gradient_steps_per_decision": cfg.agent.gradient_steps,
        "learning_starts": cfg.agent.learning_starts,
        "decisions_per_loop": cfg.train.total_steps,
    }


def ring_config(steps: int, evaluate: bool = False, env_process: bool | None = None) -> ExperimentConfig:
    """config/ring.yaml with DER lambda 0.9, ``steps`` decisions, CPU, no TensorBoard/progress/checkpoint;
    no evaluation, or (``evaluate``) ring.yaml's: 50 greedy episodes every 2,500 steps in a second process;
    ``env_process``: None = the runner's default, else forced on/off."""
    evaluation: dict[str, Any] = {"train.eval_interval": 2500, "train.eval_episodes": 50} if evaluate else {}
    if env_process is not None and has_env_process():
        evaluation["train.env_process"] = env_process
    return load_experiment_config(
        RING_YAML,
        {
            "replay.kind": "der",
            "replay.lam": 0.9,
            "train.total_steps": steps,
            "train.seed": 0,
            "train.device": "cpu",
            "train.threads": 1,
            "train.tensorboard": False,
            "train.progress": False,
            "train.save_final_checkpoint": False,
            # no greedy evaluation: SB3's loop has none, and the final one (300 episodes in a second
            # process) would count as loop time
            "train.eval_interval": 0,
            "train.final_eval_episodes": 0,
            "agent.gradient_steps": 1,
            **evaluation,
        },
    )


def env_alone(cfg: ExperimentConfig, steps: int) -> tuple[float, float, list[float], list[tuple[Any, ...]]]:
    """(env steps/s with a random policy, resets included, by wall clock and per CPU second;
    reset times in s; the transitions)."""
    env = make_env_from_config(cfg.env, cfg.train.seed)
    rng = np.random.default_rng(0)
    actions = rng.integers(0, int(env.action_space.n), size=steps)
    transitions: list[tuple[Any, ...]] = []
    resets: list[float] = []
    try:
        obs, _ = env.reset(seed=cfg.train.seed)
        t0, c0 = time.perf_counter(), time.process_time()
        for a in actions:
            next_obs, r, term, trunc, _ = env.step(int(a))
            transitions.append((obs, int(a), float(r), next_obs, bool(term), bool(trunc)))
            if term or trunc:
                t = time.perf_counter()
                next_obs, _ = env.reset()
                resets.append(time.perf_counter() - t)
            obs = next_obs
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
    finally:
        env.close()
    return steps / dt, steps / dc, resets, transitions


def learner_alone(cfg: ExperimentConfig, transitions: list[tuple[Any, ...]], updates: int) -> tuple[float, float]:
    """observe + learn calls (one gradient step each) per second and per CPU second, on a filled,
    warmed-up DER buffer."""
    obs_shape, obs_dtype = transitions[0][0].shape, transitions[0][0].dtype
    agent = DQNAgent(obs_shape, obs_dtype, 3, cfg.agent, cfg.replay, seed=0, device="cpu")
    n = len(transitions)
    warm = max(cfg.agent.learning_starts, cfg.agent.batch_size) + 500  # fill, then 500 steps promote into H2
    for k in range(warm):
        agent.observe(*transitions[k % n])
        agent.learn()
    t0, c0 = time.perf_counter(), time.process_time()
    for k in range(warm, warm + updates):
        agent.observe(*transitions[k % n])
        agent.learn()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    assert agent.grad_steps >= updates
    return updates / dt, updates / dc


def our_loop(cfg: ExperimentConfig) -> tuple[float, float, float, int, float, float]:
    """Decisions per second after learning starts (wall, CPU), of the whole run (wall), the number
    of episodes, of runner.train; and the training rate between the first episode end after learning
    starts and the last one (wall: what evaluations running beside it slow down), and the seconds
    from that last episode end to the return of train() (where it waits for pending evaluations)."""
    marks: list[tuple[float, float, int]] = []

    def on_episode(episode: int, step: int, ret: float) -> None:
        marks.append((time.perf_counter(), time.process_time(), step))

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = train(cfg, run_dir=tmp, on_episode=on_episode)
        t_end, c_end = time.perf_counter(), time.process_time()
    t1, c1, s1 = next(m for m in marks if m[2] >= cfg.agent.learning_starts)
    t_last, _c_last, s_last = marks[-1]
    n = summary.steps - s1
    training = (s_last - s1) / (t_last - t1)
    return n / (t_end - t1), n / (c_end - c1), summary.steps / (t_end - t0), summary.episodes, training, t_end - t_last


def sb3_dqn(env: Any, cfg: ExperimentConfig, steps: int, gradient_steps: int) -> Any:
    """Stable-Baselines3's DQN with this config's settings (the peer of sb3_loop and sb3_vec_loop)."""
    from stable_baselines3 import DQN

    a = cfg.agent
    return DQN(
        "MlpPolicy",
        env,
        learning_rate=a.lr,
        buffer_size=cfg.replay.capacity,
        learning_starts=a.learning_starts,
        batch_size=a.batch_size,
        tau=a.tau,
        gamma=a.gamma,
        train_freq=a.train_freq,
        gradient_steps=gradient_steps,
        target_update_interval=a.target_update_interval,
        exploration_fraction=min(1.0, a.epsilon_decay_steps / steps),
        exploration_initial_eps=a.epsilon_start,
        exploration_final_eps=a.epsilon_end,
        max_grad_norm=a.max_grad_norm,
        policy_kwargs={"net_arch": list(a.hidden_sizes)},
        seed=cfg.train.seed,
        device="cpu",
        verbose=0,
    )


def sb3_loop(cfg: ExperimentConfig) -> tuple[float, float, float]:
    """Decisions per second after learning starts (wall, CPU) and of the whole run (wall) of SB3's
    DQN with the same settings."""
    from stable_baselines3.common.callbacks import BaseCallback

    a, steps = cfg.agent, cfg.train.total_steps

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.start: tuple[float, float, int] | None = None

        def _on_step(self) -> bool:
            if self.start is None and self.num_timesteps >= a.learning_starts:
                self.start = (time.perf_counter(), time.process_time(), self.num_timesteps)
            return True

    env = make_env_from_config(cfg.env, cfg.train.seed)
    try:
        model = sb3_dqn(env, cfg, steps, gradient_steps=cfg.agent.gradient_steps)
        clock = Clock()
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps, callback=clock)
        t_end, c_end = time.perf_counter(), time.process_time()
    finally:
        env.close()
    assert clock.start is not None
    t1, c1, s1 = clock.start
    return (steps - s1) / (t_end - t1), (steps - s1) / (c_end - c1), steps / (t_end - t0)


def sb3_vec_loop(cfg: ExperimentConfig, n_envs: int) -> float:
    """Decisions per second after learning starts (wall) of SB3's DQN on a ``SubprocVecEnv`` of ``n_envs``
    envs (one gradient step per decision collected: ``gradient_steps=-1``)."""
    import functools

    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import SubprocVecEnv

    a, steps = cfg.agent, cfg.train.total_steps

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.start: tuple[float, int] | None = None

        def _on_step(self) -> bool:
            if self.start is None and self.num_timesteps >= a.learning_starts:
                self.start = (time.perf_counter(), self.num_timesteps)
            return True

    env = SubprocVecEnv([functools.partial(make_env_from_config, cfg.env, cfg.train.seed + k) for k in range(n_envs)])
    try:
        model = sb3_dqn(env, cfg, steps, gradient_steps=-1)  # SB3: -1 = as many as env steps per rollout
        clock = Clock()
        model.learn(total_timesteps=steps, callback=clock)
        t_end = time.perf_counter()
        done = model.num_timesteps
    finally:
        env.close()
    assert clock.start is not None
    t1, s1 = clock.start
    return (done - s1) / (t_end - t1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1,500 decisions per loop, 1 repeat")
    parser.add_argument("--steps", type=int, default=None, help="decisions per training loop (default 4,000)")
    parser.add_argument("--repeats", type=int, default=None, help="rounds of every part (default 3)")
    parser.add_argument("--vec-only", action="store_true",
                        help="only our loop with N = 1 and N = 2 env workers, and SB3 with SubprocVecEnv of 1 and 2")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    steps = args.steps or (1_500 if args.quick else 4_000)
    repeats = args.repeats or (1 if args.quick else 3)
    worker = default_loop_uses_worker()
    cfg = ring_config(steps, env_process=worker)
    eval_worker = default_loop_uses_worker(evaluate=True)
    eval_cfg = ring_config(steps, evaluate=True, env_process=eval_worker)
    sequential_cfg = ring_config(steps, env_process=False)
    if steps <= cfg.agent.learning_starts + 200:
        parser.error(f"--steps = {steps}, expected more than learning_starts + 200 = {cfg.agent.learning_starts + 200}")

    best: dict[str, float] = {}  # wall-clock rates, best of the repeats
    cpu: dict[str, float] = {}  # rates per CPU second of this process (steadier under load)
    whole: dict[str, float] = {}
    resets_all: list[float] = []
    episodes = 0
    rounds: list[dict[str, float]] = []  # per round: the four wall and CPU rates
    waits: list[float] = []  # per round: extra seconds train() waited for evaluations at its end

    def keep(table: dict[str, float], name: str, value: float) -> None:
        table[name] = max(table.get(name, 0.0), value)

    vec = has_num_envs()
    if args.vec_only:
        if not vec:
            parser.error("--vec-only: this checkout has no train.num_envs")
        vec_rounds: list[dict[str, float]] = []
        for r in range(repeats):
            one = our_loop(cfg)[4]  # the training rate: first to last episode end after learning starts
            run_two = our_loop(with_num_envs(cfg, 2))
            two, two_cpu = run_two[4], run_two[1]
            sb3_one, sb3_two = sb3_vec_loop(cfg, 1), sb3_vec_loop(cfg, 2)
            vec_rounds.append({"loop": one, "vec": two, "sb3_vec1": sb3_one, "sb3_vec2": sb3_two, "vec_per_trainer_cpu_s": two_cpu})
            print(f"repeat {r + 1}/{repeats}: loop N=1 {one:.0f}  N=2 {two:.0f} ({two / one:.2f}x)  SB3 SubprocVecEnv 1 "
                  f"{sb3_one:.0f}  2 {sb3_two:.0f} ({sb3_two / sb3_one:.2f}x)", file=sys.stderr, flush=True)
        med = lambda key: round(float(np.median([v[key] for v in vec_rounds])), 3)  # noqa: E731
        print(json.dumps({
            "bench": "train_loop", "parts": "vec-only", "task": task_settings(cfg), "repeats": repeats,
            "loop_per_s": round(max(v["loop"] for v in vec_rounds), 1),
            "vec_loop_per_s": round(max(v["vec"] for v in vec_rounds), 1),
            "vec_speedup": round(float(np.median([v["vec"] / v["loop"] for v in vec_rounds])), 3),
            "sb3_vec1_per_s": round(max(v["sb3_vec1"] for v in vec_rounds), 1),
            "sb3_vec2_per_s": round(max(v["sb3_vec2"] for v in vec_rounds), 1),
            "sb3_vec_speedup": round(float(np.median([v["sb3_vec2"] / v["sb3_vec1"] for v in vec_rounds])), 3),
            "rounds": [{k: round(x, 1) for k, x in v.items()} for v in vec_rounds],
            "median_loop_per_s": med("loop"), "torch_threads": torch.get_num_threads(),
        }))
        return 0

    for r in range(repeats):
        env_ps, env_cpu, resets, transitions = env_alone(cfg, steps)
        keep(best, "env", env_ps)
        keep(cpu, "env", env_cpu)
        resets_all += resets
        learner_ps, learner_cpu = learner_alone(cfg, transitions, min(steps, 2_000))
        keep(best, "learner", learner_ps)
        keep(cpu, "learner", learner_cpu)
        loop, loop_cpu, loop_whole, episodes, loop_training, loop_tail = our_loop(cfg)
        keep(best, "loop", loop)
        keep(cpu, "loop", loop_cpu)
        keep(whole, "loop", loop_whole)
        sequential, sequential_cpu, _, _, sequential_training, _ = our_loop(sequential_cfg)
        keep(best, "sequential", sequential)
        keep(cpu, "sequential", sequential_cpu)
        _, _, _, _, loop_eval, eval_tail = our_loop(eval_cfg)
        keep(best, "loop_eval", loop_eval)
        waits.append(eval_tail - loop_tail)
        if vec:
            vec_ps = our_loop(with_num_envs(cfg, 2))[4]  # the training rate, as loop_training
            keep(best, "vec", vec_ps)
            sb3_vec1, sb3_vec2 = sb3_vec_loop(cfg, 1), sb3_vec_loop(cfg, 2)
            keep(best, "sb3_vec1", sb3_vec1)
            keep(best, "sb3_vec2", sb3_vec2)
        sb3, sb3_cpu, sb3_whole = sb3_loop(cfg)
        keep(best, "sb3", sb3)
        keep(cpu, "sb3", sb3_cpu)
        keep(whole, "sb3", sb3_whole)
        rounds.append({"env": env_ps, "learner": learner_ps, "loop": loop, "loop_training": loop_training,
                       "loop_eval": loop_eval, "sequential": sequential, "sequential_training": sequential_training, "sb3": sb3, "env_cpu": env_cpu,
                       "learner_cpu": learner_cpu, "loop_cpu": loop_cpu, "sb3_cpu": sb3_cpu,
                       **({"vec": vec_ps, "sb3_vec1": sb3_vec1, "sb3_vec2": sb3_vec2} if vec else {})})  # fmt: skip
        print(
            f"repeat {r + 1}/{repeats} (per wall s / per CPU s): env {env_ps:.0f} / {env_cpu:.0f} "
            f"(reset p50 {1e3 * float(np.median(resets)):.2f} ms over {len(resets)})  learner {learner_ps:.0f} / "
            f"{learner_cpu:.0f}  loop {loop:.0f} / {loop_cpu:.0f}  sequential {sequential:.0f}  loop+eval {loop_eval:.0f}  "
            f"sb3 {sb3:.0f} / {sb3_cpu:.0f}"
            + (f"  N=2 {vec_ps:.0f} ({vec_ps / loop:.2f}x)  sb3 SubprocVecEnv 1 {sb3_vec1:.0f} 2 {sb3_vec2:.0f}" if vec else ""),
            file=sys.stderr,
            flush=True,
        )

    def limit(t: dict[str, float], suffix: str = "") -> float:
        return 1.0 / (1.0 / t["env" + suffix] + 1.0 / t["learner" + suffix])

    def paired(num: str, den: Callable[[dict[str, float]], float]) -> float:
        return round(float(np.median([r[num] / den(r) for r in rounds])), 3)

    result = {
        "bench": "train_loop",
        "env": cfg.env.id,
        "steps": steps,
        "repeats": repeats,
        "loop_per_s": round(best["loop"], 1),
        "sb3_loop_per_s": round(best["sb3"], 1),
        "env_per_s": round(best["env"], 1),
        "learner_per_s": round(best["learner"], 1),
        "limit_per_s": round(limit(best), 1),
        "reset_ms_p50": round(1e3 * float(np.median(resets_all)), 3),
        "reset_ms_mean": round(1e3 * float(np.mean(resets_all)), 3),
        "ratio_loop_vs_sb3": paired("loop", lambda r: r["sb3"]),
        "ratio_loop_vs_limit": paired("loop", limit),
        "loop_env_process": worker,
        "loop_eval_env_process": eval_worker,
        "loop_sequential_per_s": round(best["sequential"], 1),
        "ratio_sequential_vs_sb3": paired("sequential", lambda r: r["sb3"]),
        "ratio_sequential_vs_limit": paired("sequential", limit),
        "ratio_loop_vs_sequential": paired("loop", lambda r: r["sequential"]),
        "loop_eval_per_s": round(best["loop_eval"], 1),
        # against the same loop without evaluations (the evaluated run may not use the env worker)
        "eval_cost": round(1.0 - paired("loop_eval", lambda r: r["loop_training" if eval_worker == worker
                                                                 else "sequential_training"]), 3),
        "eval_wait_s": round(float(np.median(waits)), 3),
        "loop_per_cpu_s": round(cpu["loop"], 1),
        "sb3_loop_per_cpu_s": round(cpu["sb3"], 1),
        "env_per_cpu_s": round(cpu["env"], 1),
        "learner_per_cpu_s": round(cpu["learner"], 1),
        "limit_per_cpu_s": round(limit(cpu), 1),
        "ratio_loop_vs_sb3_cpu": paired("loop_cpu", lambda r: r["sb3_cpu"]),
        "ratio_loop_vs_limit_cpu": paired("loop_cpu", lambda r: limit(r, "_cpu")),
        "loop_whole_run_per_s": round(whole["loop"], 1),
        "sb3_whole_run_per_s": round(whole["sb3"], 1),
        "episodes_per_loop": episodes,
        "torch_threads": torch.get_num_threads(),
        "task": task_settings(cfg),
    }
    if vec:
        result.update({
            "vec_loop_per_s": round(best["vec"], 1),
            "vec_speedup": paired("vec", lambda r: r["loop_training"]),
            "sb3_vec1_per_s": round(best["sb3_vec1"], 1),
            "sb3_vec2_per_s": round(best["sb3_vec2"], 1),
            "sb3_vec_speedup": paired("sb3_vec2", lambda r: r["sb3_vec1"]),
        })
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
