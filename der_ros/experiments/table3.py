"""``der table3``: reproduce Table 3 of the paper (SUMO lane change: ring and urban network).

Protocol (paper section 5.1): DQN, PER and DER (lambda = 0.1 / 0.5 / 0.9) trained for 15,000
environment steps on each network; only the replay differs between methods. The environments are
``der_ros/LaneChangeRing-v0`` and ``der_ros/LaneChangeUrban-v0`` (``config/ring.yaml``,
``config/urban.yaml``); the urban network is a synthetic stand-in for the paper's Yeongdong
Bridge OpenStreetMap extract (see ``sumo_bridge/network_build.py``).

Per run:

* total reward per episode = mean return over all training episodes (the paper reports one
  "total reward" per model; we read it as the average episode return of the run),
* the same over the last 100 training episodes,
* success and collision rates over all training episodes (from the env's ``info["event"]``,
  logged by the runner as ``charts/episode_success`` / ``charts/episode_collision``).

Per method: mean over seeds with a 95% bootstrap CI (10,000 resamples, fixed seed). Writes
``<results>/table3.md`` and Fig. 5-style learning curves ``table3_ring_curves.png`` and
``table3_urban_curves.png``; run directories go to ``--out/<network>/<method>/seed<k>``
(finished runs are reused, interrupted ones resume).
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from der_ros.experiments.plots import plot_learning_curves
from der_ros.experiments.report import run_details, total_training_time, write_markdown
from der_ros.experiments.stats import CI, average_score, bootstrap_ci, mean_of_last
from der_ros.experiments.suite import (
    RunResult,
    RunSpec,
    add_suite_arguments,
    environment_info,
    load_result,
    methods_by_name,
    plan_runs,
    run_specs,
    suite_command,
    suite_overrides,
    suite_seeds,
)

__all__ = ["PAPER_TABLE3", "NETWORKS", "add_arguments", "run", "score_run", "write_table3"]

log = logging.getLogger(__name__)

#: Table 3 of the paper: network -> method -> total reward
PAPER_TABLE3: dict[str, dict[str, float]] = {
    "ring": {"dqn": 135.74, "der0.1": 117.46, "der0.5": 122.78, "der0.9": 216.91, "per": 135.71},
    "urban": {"dqn": 60.64, "der0.1": 75.84, "der0.5": 70.25, "der0.9": 81.77, "per": 79.50},
}
NETWORKS: dict[str, str] = {"ring": "Ring network", "urban": "Yeongdong Bridge (synthetic stand-in)"}
EVENT_METRICS = ("charts/episode_success", "charts/episode_collision")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_suite_arguments(parser, default_config="config/ring.yaml", default_out="runs/table3", default_seeds=5)
    parser.description = (parser.description or "") + " (--config is the ring network's training YAML)"
    parser.add_argument("--urban-config", dest="urban_config", default="config/urban.yaml",
                        help="training YAML of the urban network (default config/urban.yaml)")  # fmt: skip
    parser.add_argument("--networks", nargs="+", choices=tuple(NETWORKS), default=list(NETWORKS),
                        help="which networks to run (default: both)")  # fmt: skip


def _event_rate(run: RunResult, name: str) -> float:
    if name not in run.metrics or run.metrics[name][1].size == 0:
        return math.nan
    return float(np.mean(run.metrics[name][1]))


def score_run(run: RunResult) -> dict[str, float]:
    """Scores of one run (see the module docstring)."""
    return {
        "total_reward": average_score(run.returns),
        "last100": mean_of_last(run.returns, 100),
        "success": _event_rate(run, "charts/episode_success"),
        "collision": _event_rate(run, "charts/episode_collision"),
        "episodes": float(len(run.returns)),
    }


def _ci(values: Sequence[float]) -> CI:
    clean = [v for v in values if not math.isnan(v)]
    return bootstrap_ci(clean) if clean else CI(math.nan, math.nan, math.nan, 0)


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("eclipse-sumo", "libsumo"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def write_table3(
    results: dict[str, dict[str, list[RunResult]]],
    labels: dict[str, str],
    path: Path,
    command: str,
    seeds: Sequence[int],
    steps: dict[str, int],
    wall_s: float,
) -> Path:
    """Markdown: per network, ours (mean ± 95% CI) beside the paper's total reward."""
    lines = [
        "# Table 3 — SUMO lane change (reproduction)",
        "",
        "Total reward per episode = mean training-episode return of a run (reward, paper section 5.1:",
        "log of the mean speed of all vehicles per step, +100 for reaching the target lane, -100 for",
        "causing a collision). Ours: mean over seeds ± half-width of the 95% percentile-bootstrap CI",
        "of the mean (10,000 resamples, seed 0). Success / collision: fraction of training episodes.",
        "The urban network is a synthetic stand-in for the paper's Yeongdong Bridge OSM extract,",
        "so its numbers are not directly comparable with the paper's.",
        "",
    ]
    per_seed = [
        "| Network | Method | Seed | Episodes | Total reward | Last 100 | Success | Collision |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for net, by_method in results.items():
        lines += [
            f"## {NETWORKS[net]}",
            "",
            "| Method | Total reward (ours) | Total reward (paper) | Last 100 episodes | Success rate | Collision rate |",
            "|---|---|---|---|---|---|",
        ]
        for name, runs in by_method.items():
            scores = [score_run(r) for r in runs]
            cis = {k: _ci([s[k] for s in scores]) for k in ("total_reward", "last100", "success", "collision")}
            paper = PAPER_TABLE3[net].get(name, math.nan)
            lines.append(
                f"| {labels[name]} | {cis['total_reward'].format()} | {paper:.2f} | {cis['last100'].format()} "
                f"| {cis['success'].format(3)} | {cis['collision'].format(3)} |"
            )
            for r, s in zip(runs, scores):
                per_seed.append(
                    f"| {net} | {labels[name]} | {r.spec.seed} | {int(s['episodes'])} | {s['total_reward']:.2f} "
                    f"| {s['last100']:.2f} | {s['success']:.3f} | {s['collision']:.3f} |"
                )
        lines += ["", f"![{net} learning curves](table3_{net}_curves.png)", ""]
    info = environment_info() | _versions()
    lines += run_details(command, seeds, steps, wall_s, info, per_seed, seeds_per="method and network")
    return write_markdown(path, lines)


def run(args: argparse.Namespace) -> int:
    methods = methods_by_name(args.methods)
    seeds = suite_seeds(args)
    overrides = suite_overrides(args)
    configs = {"ring": args.config, "urban": args.urban_config}
    specs: list[RunSpec] = []
    for net in args.networks:
        specs += plan_runs(configs[net], methods, seeds, args.out, overrides, group=net)
    run_specs(specs, args.jobs)
    results: dict[str, dict[str, list[RunResult]]] = {net: {m.name: [] for m in methods} for net in args.networks}
    for spec in specs:
        results[spec.group][spec.method.name].append(load_result(spec, EVENT_METRICS))
    labels = {m.name: m.label for m in methods}
    steps = {
        net: max(int(r.summary["steps"]) for runs in by_m.values() for r in runs) for net, by_m in results.items()
    }
    out = Path(args.results)
    extra = ["--urban-config", str(args.urban_config), "--networks", *args.networks]
    md = write_table3(results, labels, out / "table3.md", suite_command("table3", args, extra), seeds, steps, total_training_time(results))
    figures = []
    for net, by_method in results.items():
        fig = out / f"table3_{net}_curves.png"
        plot_learning_curves(by_method, labels, fig, window=20, title=f"{NETWORKS[net]} (Fig. 5 style)")
        figures.append(str(fig))
    print(md.read_text())
    print(f"wrote {md}, {', '.join(figures)}")
    return 0
