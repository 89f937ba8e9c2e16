"""``der table1``: reproduce Table 1 of the paper (CartPole-v1) over several seeds.

Protocol (paper section 4.1): DQN with an MLP of 256 units, Adam lr 0.0005, gamma 0.98, batch 128,
N1 = 50,000, N2 = batch x 100, 10,000 training steps; only the replay changes between methods
(uniform = DQN, PER, DER with lambda = 0.1 / 0.5 / 0.9). Per run:

* max score     = highest moving average of 20 consecutive training-episode returns,
* average score = mean return over all training episodes;

per method: mean over seeds with a 95% bootstrap CI (10,000 resamples, fixed seed).
Writes ``<results>/table1.md``, ``table1_curves.png`` (Fig. 1 style) and ``table1_td.png``
(Fig. 2 style); run directories go to ``--out`` (finished runs are reused).
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path

from der_ros.experiments.plots import plot_learning_curves, plot_td_traces
from der_ros.experiments.report import run_details, total_training_time, write_markdown
from der_ros.experiments.stats import CI, average_score, bootstrap_ci, max_moving_average
from der_ros.experiments.suite import (
    RunResult,
    add_suite_arguments,
    environment_info,
    load_result,
    methods_by_name,
    plan_runs,
    report_interrupted,
    run_specs,
    suite_command,
    suite_overrides,
    suite_seeds,
)

__all__ = ["PAPER_TABLE1", "add_arguments", "run", "score_runs", "write_table1"]

log = logging.getLogger(__name__)

#: Table 1 of the paper: method -> (max score, average score)
PAPER_TABLE1: dict[str, tuple[float, float]] = {
    "dqn": (373.80, 229.30),
    "der0.1": (478.65, 210.58),
    "der0.5": (500.0, 259.23),
    "der0.9": (500.0, 285.49),
    "per": (500.0, 237.63),
}

TD_METRICS = ("losses/abs_td_error", "replay/h2_weight_mean", "replay/h2_size", "replay/h2_fraction")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_suite_arguments(parser, default_config="config/cartpole.yaml", default_out="runs/table1", default_seeds=5)


def score_runs(runs: Sequence[RunResult], window: int = 20) -> tuple[CI, CI]:
    """(max score CI, average score CI) over the seeds of one method."""
    max_scores = [max_moving_average(r.returns, window) for r in runs]
    avg_scores = [average_score(r.returns) for r in runs]
    return bootstrap_ci(max_scores), bootstrap_ci(avg_scores)


def write_table1(
    results: dict[str, list[RunResult]],
    labels: dict[str, str],
    path: Path,
    command: str,
    seeds: Sequence[int],
    steps: int,
    wall_s: float,
) -> Path:
    """Markdown: ours (mean ± 95% CI) beside the paper's numbers, per-seed scores, environment."""
    lines = [
        "# Table 1 — CartPole-v1 (reproduction)",
        "",
        "Max score = highest moving average of 20 consecutive episode returns; average score = mean",
        "return over all training episodes (paper section 4.1). Ours: mean over seeds ± half-width of",
        "the 95% percentile-bootstrap CI of the mean (10,000 resamples, seed 0); interval in brackets.",
        "",
        "| Method | Max score (ours) | Max score (paper) | Average score (ours) | Average score (paper) |",
        "|---|---|---|---|---|",
    ]
    per_seed = ["| Method | Seed | Episodes | Max score | Average score |", "|---|---|---|---|---|"]
    for name, runs in results.items():
        ci_max, ci_avg = score_runs(runs)
        paper = PAPER_TABLE1.get(name, (float("nan"), float("nan")))
        lines.append(
            f"| {labels[name]} | {ci_max.format_cell()} | {paper[0]:.2f} | {ci_avg.format_cell()} | {paper[1]:.2f} |"
        )
        for r in runs:
            per_seed.append(
                f"| {labels[name]} | {r.spec.seed} | {len(r.returns)} | {max_moving_average(r.returns):.2f} "
                f"| {average_score(r.returns):.2f} |"
            )
    lines += [
        "",
        "![learning curves](table1_curves.png)",
        "",
        "![TD error and H2 weight](table1_td.png)",
        "",
        *run_details(command, seeds, steps, wall_s, environment_info(), per_seed, seeds_per="method"),
    ]
    return write_markdown(path, lines)


def run(args: argparse.Namespace) -> int:
    methods = methods_by_name(args.methods)
    seeds = suite_seeds(args)
    overrides = suite_overrides(args)
    specs = plan_runs(args.config, methods, seeds, args.out, overrides)
    summaries = run_specs(specs, args.jobs)
    if report_interrupted("table1", summaries):
        return 130
    results: dict[str, list[RunResult]] = {m.name: [] for m in methods}
    for spec in specs:
        results[spec.method.name].append(load_result(spec, TD_METRICS))
    labels = {m.name: m.label for m in methods}
    steps = max(int(r.summary["steps"]) for runs in results.values() for r in runs)
    out = Path(args.results)
    md = write_table1(results, labels, out / "table1.md", suite_command("table1", args), seeds, steps, total_training_time(results))
    plot_learning_curves(results, labels, out / "table1_curves.png", window=20, title="CartPole-v1 (Fig. 1 style)")
    plot_td_traces(results, labels, out / "table1_td.png", title="CartPole-v1 (Fig. 2 style)")
    print(md.read_text())
    print(f"wrote {md}, {out / 'table1_curves.png'}, {out / 'table1_td.png'}")
    return 0
