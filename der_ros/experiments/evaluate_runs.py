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
``DIR/<method>/<seed dir>/evaluation.json`` (:class:`~der_ros.train.eval_result.EvalResult`), which
research/tuning/compare_arms.py compares situation by situation.

Under other traffic, or with the shield switched: ``--traffic YAML`` evaluates every run in the ``env``
of another training YAML (the shifted settings of config/shift/, docs/safety.md), keeping the run's
own shield; ``--safety none|rss`` takes the shield off or puts it on (the same agent unshielded /
shielded). ``--json FILE`` writes the totals per method (the run directory's parent) with the
caused-collision rate's exact 95% upper bound. Was der_ros/experiments/evaluate_runs.py (der evaluate).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
from pathlib import Path

import numpy as np
from scipy.stats import beta as beta_dist

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.configuration import ConfigError
from der_ros.safety.config import SafetyConfig
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_result import EpisodeResult, EvalResult
from der_ros.train.eval_seeds import EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE, evaluation_seeds

__all__ = ["add_arguments", "evaluate_run", "run"]

SEED_SETS = {"tuning": TUNING_EVAL_SEED_BASE, "report": EVAL_SEED_BASE}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, help="run directories holding config.yaml and checkpoint.pt")
    parser.add_argument("--episodes", type=int, default=1800, help="evaluation episodes per run (default 1800)")
    parser.add_argument("--seed-set", choices=tuple(SEED_SETS), default="tuning",
                        help="tuning: TUNING_EVAL_SEED_BASE + k (default); report: EVAL_SEED_BASE + k")  # fmt: skip
    parser.add_argument("--out", type=Path, help="also save DIR/<method>/<seed dir>/evaluation.json per run")
    parser.add_argument("--traffic", type=Path, metavar="YAML",
                        help="evaluate in the env of this training YAML (e.g. config/shift/ring_dense.yaml) instead "
                        "of the run's own; the run's shield is kept unless --safety says otherwise")  # fmt: skip
    parser.add_argument("--safety", choices=("run", "rss", "none"), default="run",
                        help="run: the run's own env.safety (default); rss: the shield on (the run's parameters "
                        "if it had them, else the defaults); none: the shield off")  # fmt: skip
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the totals per method to FILE")


def evaluation_env(run_env: EnvConfig, traffic: EnvConfig | None = None, safety: str = "run") -> EnvConfig:
    """The env a run is evaluated in: its own, or ``traffic``'s (a shifted setting) with the run's shield;
    ``safety`` ``run`` keeps that shield, ``none`` removes it, ``rss`` puts the RSS shield on (the run's
    parameters if it had an RSS shield, else the defaults)."""
    env = run_env if traffic is None else dataclasses.replace(traffic, safety=run_env.safety)
    if traffic is not None and traffic.id != run_env.id:
        raise ConfigError(f"--traffic: env.id = {traffic.id!r}, the run's is {run_env.id!r} (same env, other traffic)")
    if safety == "none":
        return dataclasses.replace(env, safety=SafetyConfig())
    if safety == "rss":
        shield = env.safety if env.safety.kind == "rss" else SafetyConfig(kind="rss")
        return dataclasses.replace(env, safety=shield)
    if safety != "run":
        raise ConfigError(f"--safety = {safety!r}, expected run, rss or none")
    return env


def upper_bound_95(k: int, n: int) -> float:
    """Exact (Clopper-Pearson) one-sided 95% upper bound of a rate seen ``k`` times in ``n`` trials
    (0 in n: 1 - 0.05^(1/n), about 3/n)."""
    if n < 1:
        return float("nan")
    if k >= n:
        return 1.0
    return float(beta_dist.ppf(0.95, k + 1, n - k))


def evaluate_run(run_dir: Path, episodes: int, seed_base: int, traffic: EnvConfig | None = None,
                 safety: str = "run") -> tuple[list[int], list[EpisodeResult]]:  # fmt: skip
    """(seeds, episodes) of ``run_dir``'s final checkpoint, greedy, one episode per evaluation seed, in
    :func:`evaluation_env` (the run's env unless ``traffic`` / ``safety`` change it).

    ConfigError naming the file when the run has no config or checkpoint, or evaluates several
    episodes per seed (its evaluations would not be the ones this seed list reproduces)."""
    for name in ("config.yaml", "checkpoint.pt"):
        if not (run_dir / name).is_file():
            raise ConfigError(f"{run_dir / name}: not found (a run directory holds config.yaml and checkpoint.pt)")
    cfg = load_experiment_config(run_dir / "config.yaml")
    cfg = dataclasses.replace(cfg, env=evaluation_env(cfg.env, traffic, safety))
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
    traffic = load_experiment_config(args.traffic).env if args.traffic is not None else None
    total: collections.Counter[str] = collections.Counter()
    by_method: dict[str, collections.Counter[str]] = {}
    for run_dir in args.runs:
        seeds, eps = evaluate_run(run_dir, args.episodes, base, traffic, args.safety)
        if args.out is not None:
            dest = args.out / run_dir.resolve().parent.name / run_dir.resolve().name
            dest.mkdir(parents=True, exist_ok=True)
            EvalResult(step=-1, episodes=eps, seeds=seeds).save(dest / "evaluation.json")
        counts = collections.Counter("caused_collision" if e.caused else e.outcome for e in eps)
        total.update(counts)
        method = by_method.setdefault(run_dir.resolve().parent.name, collections.Counter())
        method.update(counts)
        method.update(runs=1, episodes=len(eps), interventions=sum(e.interventions for e in eps))
        bad = [e.seed for e in eps if e.caused]
        print(f"{run_dir}: {args.episodes} episodes, success {counts['success']}, caused collision "
              f"{counts['caused_collision']} (seeds {bad}), time limit {counts['time_limit']}, "
              f"mean return {np.mean([e.ret for e in eps]):.2f}", flush=True)  # fmt: skip
    print(f"total over {len(args.runs)} runs: {dict(total)}")
    if args.json is not None:
        rows = {}
        for name, c in by_method.items():
            n = c["episodes"]
            rows[name] = {"runs": c["runs"], "episodes": n, "success": c["success"] / n,
                          "caused_collisions": c["caused_collision"], "caused_collision_rate": c["caused_collision"] / n,
                          "caused_collision_upper95": upper_bound_95(c["caused_collision"], n),
                          "time_limit": c["time_limit"] / n, "interventions_per_episode": c["interventions"] / n}  # fmt: skip
        setup = {"episodes_per_run": args.episodes, "seed_set": args.seed_set, "safety": args.safety,
                 "traffic": str(args.traffic) if args.traffic else None}  # fmt: skip
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"setup": setup, "methods": rows}, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
