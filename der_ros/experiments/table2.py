"""``der table2``: the paper's Table 2 protocol on Atari (River Raid, Space Invaders, Boxing, Breakout).

Paper section 5: the Atari CNN on 84x84x4 grey frames, Adam lr 0.0005, gamma 0.99, batch 128,
N1 = 50,000, N2 = batch x 100, "more than 200,000 steps"; scores are averages of 100 episode
returns. Per run we report the mean of the last 100 training-episode (whole-game, unclipped)
returns, and the best moving average of 100 episodes; per cell the mean over seeds with a 95%
bootstrap CI.

200,000 steps x 5 methods x 4 games x seeds is a GPU-machine job (``--device auto``). Each run
holds ~2.8 GB of replay (3.5 GB for DER), so the default number of parallel jobs is limited by
free memory as well as by cores. A quick end-to-end check on a CPU machine::

    der table2 --games Breakout --methods dqn --seeds 1 --steps 300 \\
        --set replay.capacity=1000 --set agent.learning_starts=100 --out /tmp/t2 --results /tmp/t2
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from der_ros.experiments.backends.dispatch import add_backend_arguments, backend_from_args, run_specs
from der_ros.experiments.stats import CI, bootstrap_ci, max_moving_average, mean_of_last
from der_ros.experiments.suite import (
    RunResult,
    RunSpec,
    add_suite_arguments,
    default_jobs,
    environment_info,
    load_result,
    methods_by_name,
    plan_runs,
    report_interrupted,
    suite_command,
    suite_overrides,
    suite_seeds,
)
from der_ros.experiments.suite_plots import plot_learning_curves, save_figure
from der_ros.experiments.table_report import run_details, total_training_time, write_markdown

__all__ = ["GAMES", "PAPER_TABLE2", "add_arguments", "run", "default_atari_jobs"]

log = logging.getLogger(__name__)

#: game label -> gymnasium id
GAMES: dict[str, str] = {
    "River Raid": "ALE/Riverraid-v5",
    "Space Invaders": "ALE/SpaceInvaders-v5",
    "Boxing": "ALE/Boxing-v5",
    "Breakout": "ALE/Breakout-v5",
}

#: Table 2 of the paper: game -> method -> score
PAPER_TABLE2: dict[str, dict[str, float]] = {
    "River Raid": {"dqn": 1437.80, "der0.1": 1404.10, "der0.5": 1294.80, "der0.9": 920.30, "per": 962.20},
    "Space Invaders": {"dqn": 292.00, "der0.1": 671.15, "der0.5": 420.35, "der0.9": 99.40, "per": 445.50},
    "Boxing": {"dqn": 25.03, "der0.1": 40.42, "der0.5": -18.19, "der0.9": 0.49, "per": 7.29},
    "Breakout": {"dqn": 52.86, "der0.1": 58.28, "der0.5": 44.31, "der0.9": 4.96, "per": 31.14},
}


def _game_key(text: str) -> str:
    return text.replace(" ", "").lower()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_suite_arguments(
        parser, default_config="config/atari.yaml", default_out="runs/table2", default_seeds=3, default_steps=200_000
    )
    parser.add_argument(
        "--games",
        nargs="+",
        default=None,
        help="games by name without spaces, e.g. Breakout SpaceInvaders (default: all four of the paper)",
    )
    add_backend_arguments(parser)


def default_atari_jobs(specs: Sequence[RunSpec]) -> int:
    """Cores, but no more runs than fit in ~80% of the available memory.

    Per run: the replay (obs + next_obs frames of H1 and H2) twice -- a checkpoint holds a copy of
    it while it is written -- plus ~1.5 GB for torch and the emulator.
    """
    import psutil

    if not specs:
        return 1
    cfg = specs[0].resolved_config()
    frame = cfg.env.frame_stack * cfg.env.screen_size * cfg.env.screen_size
    h2 = cfg.replay.h2_capacity or 100 * cfg.agent.batch_size
    replay_bytes = 2 * frame * (cfg.replay.capacity + h2)
    per_run = 2 * replay_bytes + 1_500_000_000
    fit = int(0.8 * psutil.virtual_memory().available // per_run)
    return max(1, min(default_jobs(), fit))


def _select_games(names: Sequence[str] | None) -> dict[str, str]:
    if names is None:
        return dict(GAMES)
    by_key = {_game_key(k): k for k in GAMES}
    out = {}
    for n in names:
        key = _game_key(n)
        if key not in by_key:
            raise ValueError(f"game {n!r} unknown; expected one of {', '.join(k.replace(' ', '') for k in GAMES)}")
        out[by_key[key]] = GAMES[by_key[key]]
    return out


def run(args: argparse.Namespace) -> int:
    methods = methods_by_name(args.methods)
    games = _select_games(args.games)
    seeds = suite_seeds(args)
    base = suite_overrides(args)
    specs: list[RunSpec] = []
    for game, env_id in games.items():
        specs += plan_runs(args.config, methods, seeds, args.out, {**base, "env.id": env_id}, group=_game_key(game))
    jobs = args.jobs or default_atari_jobs(specs)  # local processes; Ray places runs by their resources
    summaries = run_specs(specs, backend=backend_from_args(args, jobs=jobs), train=args.train)
    if report_interrupted("table2", summaries):
        return 130

    labels = {m.name: m.label for m in methods}
    results: dict[str, dict[str, list[RunResult]]] = {g: {m.name: [] for m in methods} for g in games}
    by_group = {_game_key(g): g for g in games}
    for spec in specs:
        results[by_group[spec.group]][spec.method.name].append(load_result(spec, ()))

    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(games), figsize=(5.5 * len(games), 4.2), squeeze=False)
    for ax, game in zip(axes[0], games):
        plot_learning_curves(results[game], labels, None, window=100, title=game, ax=ax)
    save_figure(fig, out / "table2_curves.png", dpi=110)

    extra = ["--games", *[_game_key(g) for g in games]] if args.games else []
    md = _write_table2(results, labels, out / "table2.md", suite_command("table2", args, extra), seeds, total_training_time(results))
    print(md.read_text())
    print(f"wrote {md}, {out / 'table2_curves.png'}")
    return 0


def _cell(ci: CI) -> str:
    return ci.format_cell()


def _write_table2(
    results: dict[str, dict[str, list[RunResult]]],
    labels: dict[str, str],
    path: Path,
    command: str,
    seeds: Sequence[int],
    wall_s: float,
) -> Path:
    names = list(next(iter(results.values())).keys())
    head = "| Game | " + " | ".join(f"{labels[n]} (ours) | {labels[n]} (paper)" for n in names) + " |"
    sep = "|---|" + "---|---|" * len(names)
    avg_rows, max_rows, per_seed = (
        [head, sep],
        ["| Game | " + " | ".join(labels[n] for n in names) + " |", "|---|" + "---|" * len(names)],
        [
            "| Game | Method | Seed | Steps | Episodes | Mean of last 100 | Best MA100 |",
            "|---|---|---|---|---|---|---|",
        ],
    )
    steps_seen = []
    for game, by_method in results.items():
        cells, max_cells = [], []
        for n in names:
            runs = by_method[n]
            steps_seen += [int(r.summary["steps"]) for r in runs]
            ci = bootstrap_ci([mean_of_last(r.returns, 100) for r in runs])
            ci_max = bootstrap_ci([max_moving_average(r.returns, 100) for r in runs])
            paper = PAPER_TABLE2.get(game, {}).get(n, float("nan"))
            cells.append(f"{_cell(ci)} | {paper:.2f}")
            max_cells.append(_cell(ci_max))
            for r in runs:
                per_seed.append(
                    f"| {game} | {labels[n]} | {r.spec.seed} | {int(r.summary['steps'])} | {len(r.returns)} "
                    f"| {mean_of_last(r.returns, 100):.2f} | {max_moving_average(r.returns, 100):.2f} |"
                )
        avg_rows.append(f"| {game} | " + " | ".join(cells) + " |")
        max_rows.append(f"| {game} | " + " | ".join(max_cells) + " |")
    lines = [
        "# Table 2 — Atari (paper protocol)",
        "",
        "Score = mean of the last 100 training-episode returns (whole games, unclipped), mean over seeds",
        "± half-width of the 95% bootstrap CI (10,000 resamples); interval in brackets. Paper numbers beside.",
        "",
        *avg_rows,
        "",
        "Best moving average of 100 episodes (ours):",
        "",
        *max_rows,
        "",
        "![learning curves](table2_curves.png)",
        "",
    ]
    steps = int(np.max(steps_seen)) if steps_seen else 0
    lines += run_details(command, seeds, steps, wall_s, environment_info(), per_seed)
    return write_markdown(path, lines)
