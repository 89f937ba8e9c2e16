"""``der evaluate``: re-evaluate trained runs' final checkpoints greedily on more evaluation episodes.

A run's final evaluation has ``train.final_eval_episodes`` episodes (300 in the sweeps); when every
run of two settings sits near 0 caused collisions, that cannot tell them apart. This runs each
run's ``checkpoint.pt`` greedily on the first ``--episodes`` evaluation seeds and prints success /
caused collision / time-limit counts per run and in total:

    der evaluate RUN_DIR [RUN_DIR ...] [--episodes 1800] [--seed-set tuning|report] [--out DIR]

``--seed-set tuning`` (default) uses the tuning evaluation seeds (``TUNING_EVAL_SEED_BASE + k``: what
a sweep with ``train.final_eval_episodes = --episodes`` would use, so the first ones are the sweep's
own); ``report`` the report evaluation seeds (``EVAL_SEED_BASE + k``), for a finished report run
(the first ones are then the table's own evaluation). ``--out DIR`` also saves each run's episodes as
``DIR/<method>/<seed dir>/evaluation.json`` (:class:`~der_ros.train.evaluation.EvalResult`), which
research/tuning/compare_arms.py compares situation by situation. Was der_ros/experiments/evaluate_runs.py (der evaluate).
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.configuration import ConfigError
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.evaluation import (
    EVAL_SEED_BASE,
    TUNING_EVAL_SEED_BASE,
    EpisodeResult,
    EvalResult,
    GreedyQPolicy,
    evaluation_seeds,
    run_episodes,
)

__all__ = ["add_arguments", "evaluate_run", "run"]

SEED_SETS = {"tuning": TUNING_EVAL_SEED_BASE, "report": EVAL_SEED_BASE}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    parser.add_argument("--episodes", type=int, default=1800, help="evaluation episodes per run (default 1800)")
    parser.add_argument("--seed-set", choices=tuple(SEED_SETS), default="tuning",
                        help="tuning: TUNING_EVAL_SEED_BASE + k (default); report: EVAL_SEED_BASE + k")  # fmt: skip
    parser.add_argument("--out", type=Path, help="also save DIR/<method>/<seed dir>/evaluation.json per run")


def evaluate_run(run_dir: Path, episodes: int, seed_base: int) -> tuple[list[int], list[EpisodeResult]]:
    """(seeds, episodes) of ``run_dir``'s final checkpoint, greedy, one episode per evaluation seed.

    ConfigError naming the file when the run has no config or checkpoint, or evaluates several
    episodes per seed (its evaluations would not be the ones this seed list reproduces)."""
    for name in ("config.yaml", "checkpoint.pt"):
        if not (run_dir / name).is_file():
            raise ConfigError(f"{run_dir / name}: not found (a run directory holds config.yaml and checkpoint.pt)")
    cfg = load_experiment_config(run_dir / "config.yaml")
    if cfg.train.eval_episodes_per_seed != 1:
        raise ConfigError(f"{run_dir / 'config.yaml'}: train.eval_episodes_per_seed = "
                          f"{cfg.train.eval_episodes_per_seed}, expected 1")  # fmt: skip
    seeds = evaluation_seeds(episodes, seed_base)
    agent = DQNAgent.load(run_dir / "checkpoint.pt")
    agent.q_net.eval()
    env = make_env_from_config(cfg.env, seed_base)  # libsumo: one simulation per process
    try:
        return seeds, run_episodes(GreedyQPolicy(agent.q_net, np.float32), [env], seeds, episodes)
    finally:
        env.close()


def run(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise ConfigError(f"--episodes = {args.episodes}, expected >= 1")
    base = SEED_SETS[args.seed_set]
    total: collections.Counter[str] = collections.Counter()
    for run_dir in args.runs:
        seeds, eps = evaluate_run(run_dir, args.episodes, base)
        if args.out is not None:
            dest = args.out / run_dir.resolve().parent.name / run_dir.resolve().name
            dest.mkdir(parents=True, exist_ok=True)
            EvalResult(step=-1, episodes=eps, seeds=seeds).save(dest / "evaluation.json")
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        bad = [e.seed for e in eps if e.caused]
        print(f"{run_dir}: {args.episodes} episodes, success {counts['success']}, caused collision "
              f"{counts['caused_collision']} (seeds {bad}), time limit {counts['time_limit']}, "
              f"mean return {np.mean([e.ret for e in eps]):.2f}", flush=True)  # fmt: skip
    print(f"total over {len(args.runs)} runs: {dict(total)}")
    return 0
