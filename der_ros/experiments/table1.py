"""``der table1``: Table 1 of the paper (CartPole-v1) over several seeds, evaluated greedily too.

Protocol (paper section 4.1): DQN with an MLP of 256 units, Adam lr 0.0005, gamma 0.98, batch 128,
N1 = 50,000, N2 = batch x 100, 10,000 training steps; only the replay changes between methods
(uniform = DQN, PER, DER with lambda = 0.1 / 0.5 / 0.9). Per run:

* max score     = highest moving average of 20 consecutive training-episode returns (the paper's
  "max score", max MA20),
* average score = mean return over all training episodes,
* greedy return = mean return of the greedy policy (epsilon = 0) after training on 300 held-out
  evaluation episodes (seeds never used in training); periodic evaluations give the curves.

Per method: IQM over seeds with stratified-bootstrap 95% CIs (rliable) and the mean with its CI;
the probability of improvement of each DER lambda over DQN and over PER; baselines (random,
constant, a scripted rule) on the same evaluation episodes. Writes ``<results>/table1.md``,
``table1.json``, ``table1_curves.png`` and ``table1_td.png`` (Fig. 2 style); run directories go
to ``--out`` (finished runs are reused).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from der_ros.experiments.aggregate import (
    final_evaluation,
    iqm_interval,
    mean_interval,
    probability_of_improvement,
    significance_sentence,
)
from der_ros.experiments.backends.dispatch import add_backend_arguments, backend_from_args, run_specs
from der_ros.experiments.baselines import BaselineJob, baseline_names, run_baselines
from der_ros.experiments.stats import average_score, max_moving_average
from der_ros.experiments.suite import (
    RunResult,
    add_suite_arguments,
    environment_info,
    load_result,
    methods_by_name,
    plan_runs,
    report_interrupted,
    suite_command,
    suite_overrides,
    suite_seeds,
)
from der_ros.experiments.suite_plots import plot_eval_curves, plot_td_traces
from der_ros.experiments.table_report import run_details, total_training_time, write_markdown
from der_ros.train.config import load_experiment_config
from der_ros.train.eval_result import EvalResult

__all__ = ["PAPER_TABLE1", "BASELINE_LABELS", "add_arguments", "run", "score_run", "write_table1"]

log = logging.getLogger(__name__)

#: Table 1 of the paper: method -> (max score, average score)
PAPER_TABLE1: dict[str, tuple[float, float]] = {
    "dqn": (373.80, 229.30),
    "der0.1": (478.65, 210.58),
    "der0.5": (500.0, 259.23),
    "der0.9": (500.0, 285.49),
    "per": (500.0, 237.63),
}

BASELINE_LABELS = {"random": "random", "constant": "always push left", "scripted": "scripted (angle + 0.5 x angular velocity)"}
COMPARISONS = [(f"der{lam}", ref) for lam in ("0.1", "0.5", "0.9") for ref in ("dqn", "per")]

TD_METRICS = ("losses/abs_td_error", "replay/h2_weight_mean", "replay/h2_size", "replay/h2_fraction")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_suite_arguments(parser, default_config="config/cartpole.yaml", default_out="runs/table1", default_seeds=10)
    parser.add_argument("--no-baselines", dest="baselines", action="store_false", help="skip the baseline rows")
    add_backend_arguments(parser)


def score_run(run: RunResult) -> dict[str, float]:
    """Per-run scores: the paper's two training metrics and the final greedy evaluation."""
    ev = final_evaluation(run.spec.run_dir)
    return {"max_ma20": max_moving_average(run.returns, 20), "avg_score": average_score(run.returns),
            "eval_return": ev.mean_return if ev else math.nan, "episodes": float(len(run.returns))}  # fmt: skip


def write_table1(
    results: dict[str, list[RunResult]],
    labels: dict[str, str],
    baselines: dict[str, EvalResult],
    path: Path,
    command: str,
    seeds: Sequence[int],
    steps: int,
    wall_s: float,
) -> tuple[Path, Path]:
    """``table1.md`` (ours beside the paper's numbers, baselines, significance) and ``table1.json``."""
    scores = {name: [score_run(r) for r in runs] for name, runs in results.items()}
    lines = [
        "# Table 1 — CartPole-v1 (reproduction)",
        "",
        "Max score = highest moving average of 20 consecutive **training**-episode returns, average score = mean",
        "return over all training episodes (the paper's metrics, section 4.1; exploration included). Greedy return",
        "= the greedy policy (ε = 0) after training on 300 held-out evaluation episodes (seeds never used in",
        "training). Ours: **IQM over training seeds [95% stratified-bootstrap CI]** (rliable); the mean ± CI",
        "follows below.",
        "",
        "| Method | Max score (ours, IQM) | Max score (paper) | Average score (ours, IQM) | Average score (paper) | Greedy return (IQM) |",
        "|---|---|---|---|---|---|",
    ]
    per_seed = ["| Method | Seed | Episodes | Max score | Average score | Greedy return |", "|---|---|---|---|---|---|"]
    payload: dict[str, Any] = {"cartpole": {}}
    for name, per in scores.items():
        col = {k: [s[k] for s in per] for k in ("max_ma20", "avg_score", "eval_return")}
        payload["cartpole"][name] = {"seeds": [r.spec.seed for r in results[name]], **col}
        paper = PAPER_TABLE1.get(name, (math.nan, math.nan))
        lines.append(
            f"| {labels[name]} (n={len(per)}) | {iqm_interval(col['max_ma20']).format(1)} | {paper[0]:.2f} "
            f"| {iqm_interval(col['avg_score']).format(1)} | {paper[1]:.2f} | {iqm_interval(col['eval_return']).format(1)} |"
        )
        for r, sc in zip(results[name], per):
            per_seed.append(f"| {labels[name]} | {r.spec.seed} | {int(sc['episodes'])} | {sc['max_ma20']:.2f} "
                            f"| {sc['avg_score']:.2f} | {sc['eval_return']:.2f} |")  # fmt: skip
    for bname, res in baselines.items():
        payload["cartpole"][bname] = {"eval_return": res.mean_return, "episodes": float(res.n)}
        lines.append(f"| *baseline:* {BASELINE_LABELS.get(bname, bname)} | — | — | — | — | {res.mean_return:.1f} |")
    lines += ["", "Mean over seeds [95% CI]:", "", "| Method | Max score | Average score | Greedy return |", "|---|---|---|---|"]
    for name in scores:
        col = payload["cartpole"][name]
        lines.append(f"| {labels[name]} | {mean_interval(col['max_ma20']).format(1)} "
                     f"| {mean_interval(col['avg_score']).format(1)} | {mean_interval(col['eval_return']).format(1)} |")  # fmt: skip
    pairs = [(x, y) for x, y in COMPARISONS if x in scores and y in scores]
    if pairs:
        lines += ["", "Is DER better? Probability of improvement P(X > Y) over training seeds [95% CI] (rliable):", "",
                  "| X vs Y | P(X > Y) on max score | P(X > Y) on greedy return |", "|---|---|---|"]  # fmt: skip
        sentences = []
        for x, y in pairs:
            px = probability_of_improvement(payload["cartpole"][x]["max_ma20"], payload["cartpole"][y]["max_ma20"])
            pr = probability_of_improvement(payload["cartpole"][x]["eval_return"], payload["cartpole"][y]["eval_return"])
            lines.append(f"| {labels[x]} vs {labels[y]} | {px.format(2)} | {pr.format(2)} |")
            n = min(len(scores[x]), len(scores[y]))
            sentences.append(significance_sentence(labels[x], labels[y], px, "max score", n))
        lines += ["", *[f"- {t}" for t in sentences]]
    lines += [
        "",
        "![evaluation and learning curves](table1_curves.png)",
        "",
        "![TD error and H2 weight](table1_td.png)",
        "",
        *run_details(command, seeds, steps, wall_s, environment_info() | {"rliable": _version("rliable")}, per_seed,
                     seeds_per="method"),
    ]  # fmt: skip
    md = write_markdown(path, lines)
    js = path.with_suffix(".json")
    tmp = js.with_name(f".{js.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=1))
    tmp.replace(js)
    return md, js


def _version(pkg: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(pkg)
    except PackageNotFoundError:
        return "not installed"


def run(args: argparse.Namespace) -> int:
    methods = methods_by_name(args.methods)
    seeds = suite_seeds(args)
    overrides = suite_overrides(args)
    specs = plan_runs(args.config, methods, seeds, args.out, overrides)
    summaries = run_specs(specs, backend=backend_from_args(args), train=args.train)
    if report_interrupted("table1", summaries):
        return 130
    results: dict[str, list[RunResult]] = {m.name: [] for m in methods}
    for spec in specs:
        results[spec.method.name].append(load_result(spec, TD_METRICS))
    baselines: dict[str, EvalResult] = {}
    if args.baselines:
        cfg = load_experiment_config(args.config, overrides or None)
        episodes = cfg.train.final_eval_episodes or cfg.train.eval_episodes
        jobs = [BaselineJob(cfg.env, name, episodes, cfg.train.eval_episodes_per_seed, cfg.train.eval_seed_base, None,
                            str(Path(args.out) / "baselines" / name)) for name in baseline_names(cfg.env)]  # fmt: skip
        done = run_baselines(jobs, args.jobs)
        baselines = {j.name: done[j.out_dir] for j in jobs}
    labels = {m.name: m.label for m in methods}
    steps = max(int(r.summary["steps"]) for runs in results.values() for r in runs)
    out = Path(args.results)
    md, js = write_table1(results, labels, baselines, out / "table1.md", suite_command("table1", args), seeds, steps,
                          total_training_time(results))  # fmt: skip
    marks = {BASELINE_LABELS[b]: {"mean_return": r.mean_return} for b, r in baselines.items() if b == "scripted"}
    plot_eval_curves(results, labels, out / "table1_curves.png", metrics=("mean_return",), baselines=marks,
                     title="CartPole-v1: greedy evaluation (IQM over seeds) and training returns (Fig. 1 style)")  # fmt: skip
    plot_td_traces(results, labels, out / "table1_td.png", title="CartPole-v1 (Fig. 2 style)")
    print(md.read_text())
    print(f"wrote {md}, {js}, {out / 'table1_curves.png'}, {out / 'table1_td.png'}")
    return 0
