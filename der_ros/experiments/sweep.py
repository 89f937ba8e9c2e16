"""``der sweep``: a grid of config overrides x training seeds, run like a table suite.

    der sweep config/ring.yaml --grid agent.gamma=0.9,0.95,0.98 --grid agent.epsilon_decay_steps=2500,5000 \\
        --seeds 3 --first-seed 100 --set replay.kind=uniform

Every grid point is one "method" of the suite machinery (:mod:`der_ros.experiments.suite`): run
directories ``<out>/<point>/seed<k>/``, finished runs skipped, interrupted ones resumed. At the
end ``<results>/sweep.md`` ranks the points by the IQM over seeds of the final greedy evaluation
(``--rank-by``), and ``sweep.json`` holds every per-seed number. This is how we chose the settings
the paper leaves open (on tuning seeds and tuning evaluation seeds only; see docs/evaluation.md).

A sweep is tuning, so its greedy evaluations run on the **tuning** evaluation seeds
(``TUNING_EVAL_SEED_BASE + k``) unless ``--set train.eval_seed_base=...`` says otherwise: the
report's evaluation episodes never inform a choice.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from der_ros.configuration import ConfigError
from der_ros.experiments.aggregate import final_evaluation, iqm_interval
from der_ros.experiments.aggregate import iqm as iqm_point
from der_ros.experiments.backends.dispatch import add_backend_arguments, backend_from_args, run_specs
from der_ros.experiments.stats import average_score, max_moving_average
from der_ros.experiments.suite import (
    Method,
    RunResult,
    environment_info,
    load_result,
    plan_runs,
)
from der_ros.experiments.table_report import write_markdown
from der_ros.train.config import add_set_argument, parse_assignments
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE
from der_ros.yaml_loader import YamlError, load_yaml_text

__all__ = ["add_arguments", "run", "parse_grid", "grid_methods", "score_sweep_run", "RANK_KEYS"]

#: per-run scores a sweep can rank by
RANK_KEYS = ("eval_return", "eval_success", "max_ma20", "avg_score")


def _split_values(text: str) -> list[str]:
    """Split 'a,b,[1,2]' on commas outside brackets/braces."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return [v.strip() for v in out if v.strip()]


def parse_grid(items: Sequence[str]) -> list[tuple[str, list[Any]]]:
    """``["section.key=v1,v2", ...]`` -> ``[("section.key", [v1, v2]), ...]`` (values parsed as YAML)."""
    grid: list[tuple[str, list[Any]]] = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"command line: --grid {item!r}, expected section.key=value1,value2,...")
        key, raw = item.split("=", 1)
        key = key.strip()
        if "." not in key:
            raise ConfigError(f"command line: --grid {item!r}, expected section.key=... (e.g. agent.gamma=0.9,0.98)")
        values = []
        for v in _split_values(raw):
            try:
                values.append(load_yaml_text(v, f"command line: --grid {key}"))
            except YamlError as exc:
                raise ConfigError(str(exc)) from None
        if not values:
            raise ConfigError(f"command line: --grid {item!r} has no values")
        if any(k == key for k, _ in grid):
            raise ConfigError(f"command line: --grid {key} given twice")
        grid.append((key, values))
    return grid


def _slug(key: str, value: Any) -> str:
    name = key.split(".")[-1]
    text = json.dumps(value) if not isinstance(value, str) else value
    return f"{name}={text}".replace("/", "_").replace(" ", "")


def grid_methods(grid: list[tuple[str, list[Any]]]) -> list[Method]:
    """One :class:`Method` per point of the cartesian product (no grid: one point, 'base')."""
    if not grid:
        return [Method("base", "base", ())]
    keys = [k for k, _ in grid]
    methods = []
    for combo in itertools.product(*(vals for _, vals in grid)):
        name = ",".join(_slug(k, v) for k, v in zip(keys, combo))
        methods.append(Method(name, name, tuple(zip(keys, combo))))
    return methods


def score_sweep_run(run: RunResult) -> dict[str, float]:
    """Per-run scores: the final greedy evaluation and the paper's training-episode metrics."""
    ev = final_evaluation(run.spec.run_dir)
    return {
        "eval_return": ev.mean_return if ev else math.nan,
        "eval_success": ev.success_rate if ev else math.nan,
        "eval_collision": ev.collision_rate if ev else math.nan,
        "eval_time_limit": ev.time_limit_rate if ev else math.nan,
        "max_ma20": max_moving_average(run.returns, 20),
        "avg_score": average_score(run.returns),
        "episodes": float(len(run.returns)),
        "wall_time_s": float(run.summary.get("wall_time_s", math.nan)),
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="training YAML every run starts from")
    parser.add_argument("--grid", action="append", default=[], metavar="SECTION.KEY=V1,V2,...",
                        help="values to sweep for one config field (repeatable: the cartesian product)")  # fmt: skip
    parser.add_argument("--seeds", type=int, default=3, help="training seeds per grid point (default 3)")
    parser.add_argument("--first-seed", dest="first_seed", type=int, default=100,
                        help="seeds are first..first+seeds-1 (default 100: the tuning seeds)")  # fmt: skip
    parser.add_argument("--jobs", type=int, default=None, help="parallel runs (default: number of cores)")
    parser.add_argument("--out", default="runs/sweep", help="folder of the run directories (default runs/sweep)")
    parser.add_argument("--results", default=None, help="folder for sweep.md / sweep.json (default: --out)")
    parser.add_argument("--rank-by", dest="rank_by", choices=RANK_KEYS, default="eval_return",
                        help="score that ranks the grid points (IQM over seeds; default eval_return)")  # fmt: skip
    add_set_argument(parser, help="config override for every run; VALUE is YAML (repeatable)")
    add_backend_arguments(parser)


def _mean(values: Sequence[float]) -> float:
    clean = [v for v in values if not math.isnan(v)]
    return sum(clean) / len(clean) if clean else math.nan


def sweep_command(args: argparse.Namespace) -> str:
    parts = ["der", "sweep", str(args.config)]
    for g in args.grid:
        parts += ["--grid", g]
    parts += ["--seeds", str(args.seeds), "--first-seed", str(args.first_seed), "--out", str(args.out)]
    if args.results:
        parts += ["--results", str(args.results)]
    parts += ["--rank-by", args.rank_by]
    for s in args.set_values:
        parts += ["--set", s]
    return shlex.join(parts)


def write_sweep(
    results: dict[str, list[RunResult]], methods: list[Method], out: Path, command: str, seeds: Sequence[int],
    rank_by: str, eval_seed_base: int = TUNING_EVAL_SEED_BASE,
) -> Path:
    """``sweep.md`` (points ranked by IQM of ``rank_by``) and ``sweep.json`` (every per-seed score)."""
    scores = {name: [score_sweep_run(r) for r in runs] for name, runs in results.items()}
    rows = []
    for m in methods:
        per = scores[m.name]
        rank = iqm_interval([s[rank_by] for s in per])
        rows.append((rank.value if not math.isnan(rank.value) else -math.inf, m, per, rank))
    rows.sort(key=lambda r: -r[0])
    lines = [
        "# Sweep",
        "",
        f"Ranked by the IQM over seeds of `{rank_by}` (95% stratified-bootstrap CI). Eval columns: the final",
        "greedy evaluation of each run (IQM over seeds); training columns: the paper's metrics over training",
        "episodes (mean over seeds).",
        "",
        f"| Rank | Point | {rank_by} IQM [95% CI] | eval success | eval collision | eval return | max MA20 | average score |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, (_, m, per, rank) in enumerate(rows, 1):
        def iqm(key: str, digits: int = 3, per: list[dict[str, float]] = per) -> str:
            values = [s[key] for s in per if not math.isnan(s[key])]
            return "n/a" if not values else f"{float(iqm_point(values)):.{digits}f}"

        lines.append(
            f"| {i} | `{m.name}` | {rank.format(3)} | {iqm('eval_success')} | {iqm('eval_collision')} "
            f"| {iqm('eval_return', 2)} | {_mean([s['max_ma20'] for s in per]):.2f} "
            f"| {_mean([s['avg_score'] for s in per]):.2f} |"
        )
    lines += ["", "## Runs", "", f"- command: `{command}`", f"- seeds: {', '.join(map(str, seeds))}",
              f"- evaluation seeds: {eval_seed_base} + k"]
    lines += [f"- {k}: {v}" for k, v in environment_info().items()]
    lines += ["", "## Per seed", "", "| Point | Seed | " + " | ".join(RANK_KEYS) + " | eval collision |",
              "|---|---|" + "---|" * (len(RANK_KEYS) + 1)]  # fmt: skip
    for m in methods:
        for r, s in zip(results[m.name], scores[m.name]):
            lines.append(f"| `{m.name}` | {r.spec.seed} | " + " | ".join(f"{s[k]:.3f}" for k in RANK_KEYS)
                         + f" | {s['eval_collision']:.3f} |")  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    payload = {
        "command": command,
        "seeds": list(seeds),
        "rank_by": rank_by,
        "eval_seed_base": eval_seed_base,
        "points": {m.name: {"overrides": dict(m.overrides), "seeds": [r.spec.seed for r in results[m.name]],
                            **{k: [s[k] for s in scores[m.name]] for k in scores[m.name][0]}}
                   for m in methods if scores[m.name]},
    }  # fmt: skip
    (out / "sweep.json").write_text(json.dumps(payload, indent=1))
    return write_markdown(out / "sweep.md", lines)


def run(args: argparse.Namespace) -> int:
    methods = grid_methods(parse_grid(args.grid))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    overrides = dict(parse_assignments(args.set_values, "command line", label="--set"))
    overrides.setdefault("train.eval_seed_base", TUNING_EVAL_SEED_BASE)  # tuning never sees the report's episodes
    specs = plan_runs(args.config, methods, seeds, args.out, overrides)
    summaries = run_specs(specs, backend=backend_from_args(args))
    if any(s.get("interrupted") for s in summaries):
        print("der sweep: interrupted; rerun the same command to continue")
        return 130
    results: dict[str, list[RunResult]] = {m.name: [] for m in methods}
    for spec in specs:
        results[spec.method.name].append(load_result(spec, ()))
    md = write_sweep(results, methods, Path(args.results or args.out), sweep_command(args), seeds, args.rank_by,
                     int(overrides["train.eval_seed_base"]))
    print(md.read_text())
    print(f"wrote {md}")
    return 0
