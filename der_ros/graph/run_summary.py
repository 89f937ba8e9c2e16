"""The end of a ``der graph`` run: final counts, plots, ``summary.json`` and the summary table.

The counts come from what the run left behind, not from the live monitor: the bridge's own
summary line in its log (simulated steps, commands, events) and the recorded bag (episode events
and topic counts through :mod:`der_ros.bag`; complete, since the recorder stops last). The
monitor only sees what arrives after its own discovery finished, so a short run can start
before it matched the bridge.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import re
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from der_ros.bag.reader import BagError, BagReader
from der_ros.bag.writer import read_episode_summary
from der_ros.contract import COMMAND, EPISODE_COLLISION, EPISODE_START, EPISODE_SUCCESS, EPISODE_TIME_LIMIT
from der_ros.graph.greedy_episode import GreedyEpisode
from der_ros.graph.run_progress import ProgressSnapshot
from der_ros.graph.supervisor import RunOutcome
from der_ros.offline.bag_plots import plot_bags
from der_ros.train.eval_result import EvalResult

__all__ = ["bridge_summary", "snapshot_from_bag", "report"]

log = logging.getLogger("der.graph")


def _fallback_plot(returns: list[float], out_dir: Path) -> list[Path]:
    """Episode returns with a moving average (used when the bag tools cannot plot)."""
    if not returns:
        return []
    import matplotlib  # lazy: matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    r = np.asarray(returns, dtype=np.float64)
    w = min(10, len(r))
    avg = np.convolve(r, np.ones(w) / w, mode="valid")
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(np.arange(1, len(r) + 1), r, ".", alpha=0.4, label="episode return")
    ax.plot(np.arange(w, len(r) + 1), avg, "-", label=f"moving average ({w})")
    ax.set_xlabel("episode")
    ax.set_ylabel("return")
    ax.legend()
    path = out_dir / "returns.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def _plots(bag: Path, returns: list[float], out_dir: Path) -> list[Path]:
    try:
        written = plot_bags([bag], out_dir)
        if written:
            return list(written)
    except Exception as exc:  # plotting must not turn a finished run into a failure
        log.warning("bag plots failed (%s); plotting the monitored returns instead", exc)
    return _fallback_plot(returns, out_dir)


def _logged_summary(log_dir: Path, node: str, label: str) -> dict[str, float]:
    """The last ``<label> summary: {json}`` line a node logs when it stops ({} if absent)."""
    for name in (f"{node}.log", "graph.log"):
        path = log_dir / name
        if path.is_file():
            found = re.findall(label + r" summary: (\{.*\})", path.read_text(errors="replace"))
            if found:
                try:
                    return dict(json.loads(found[-1]))
                except json.JSONDecodeError:
                    return {}
    return {}


def bridge_summary(log_dir: Path) -> dict[str, float]:
    """The JSON summary line the bridge logs when it stops ({} if absent)."""
    return _logged_summary(log_dir, "bridge_node", "bridge")


def safety_summary(log_dir: Path) -> dict[str, float]:
    """The JSON summary line the safety node logs when it stops ({} if absent)."""
    return _logged_summary(log_dir, "safety_node", "safety")


def unanswered_run(outcome: RunOutcome, bridge: dict[str, float]) -> RunOutcome:
    """A run whose nodes all exited 0 but whose agent answered none of the bridge's steps is a failure.

    The bridge then drove every step with its default action on the timeout: the bag holds no
    command and the checkpoint learned nothing worth keeping, though every process "succeeded"
    (seen once in CI: 62 states, 0 commands, summary ok). Judged from the bridge's own counters;
    without a bridge summary (a node died) the outcome is left as it is.
    """
    steps = int(bridge.get("sim_steps", 0))
    if not outcome.ok or steps == 0 or "commands/accepted" not in bridge or bridge["commands/accepted"] > 0:
        return outcome
    rejected = {k.split("/", 1)[1]: int(v) for k, v in bridge.items()
                if k.startswith("commands/") and k not in ("commands/accepted", "commands/opened") and v}
    return dataclasses.replace(outcome, ok=False, reason=(
        f"the agent answered none of the bridge's {steps} steps (bridge counters {rejected or 'all 0'}); every step "
        "ran on the command timeout: see logs/agent_node.log and logs/bridge_node.log"))


def snapshot_from_bag(bag: Path, live: ProgressSnapshot | None) -> ProgressSnapshot | None:
    """Final counts from the recorded bag (complete: the recorder stopped last), else the live ones:
    decision steps = recorded commands, episodes and outcomes from the bag's episode summary."""
    if not bag.is_dir():
        return live
    error: Exception | None = None
    # a killed recorder's bag warns: one log line each, never Python's raw "file:line: Category: ..." print
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            counts = BagReader(bag).topic_counts()
            events = read_episode_summary(bag)
        except (BagError, OSError) as exc:
            error = exc
    for w in caught:
        log.warning("%s", w.message)
    if error is not None:
        log.warning("could not read the bag summary (%s); using the live counts", error)
        return live
    if counts is None:
        return live
    snap = ProgressSnapshot(metrics=dict(live.metrics) if live is not None else {})
    snap.steps = sum(c for name, c in counts.items() if name.rsplit("/", 1)[-1] == COMMAND)
    for e in events:
        if e.get("event") == EPISODE_START:
            continue
        snap.episodes += 1
        if e.get("event") in snap.outcomes:
            snap.outcomes[e["event"]] += 1
        if isinstance(e.get("return"), (int, float)):
            snap.returns.append(float(e["return"]))
        if isinstance(e.get("lane_changes"), (int, float)):
            snap.lane_changes += int(e["lane_changes"])
    return snap


def _replay_text(params: dict[str, Any]) -> str:
    agent = params.get("agent_node", {}).get("ros__parameters", {})
    kind = agent.get("replay.kind", "der")
    return f"{kind} (lambda {agent.get('replay.lam', 0.5)})" if kind == "der" else str(kind)


def report(outcome: RunOutcome, snap: ProgressSnapshot | None, run_dir: Path, wall: float, args: argparse.Namespace,
           params: dict[str, Any], bridge: dict[str, float], evaluation: EvalResult | None = None,
           greedy: GreedyEpisode | None = None, safety: dict[str, float] | None = None) -> int:
    """Write ``summary.json`` and the plots, print the table and the paths; returns the exit code
    (0 finished, 130 interrupted, 1 failed)."""
    bag = run_dir / "bag"
    ckpt = run_dir / "agent.pt"
    plots: list[Path] = []
    if not args.no_plots and bag.exists() and outcome.reason in ("finished", "stopped", "interrupted"):
        plots = _plots(bag, snap.returns if snap else [], run_dir / "plots")
    summary = {
        "outcome": outcome.reason,
        "ok": outcome.ok,
        "exit_codes": outcome.exit_codes,
        "wall_seconds": round(wall, 2),
        "steps": snap.steps if snap else 0,
        "episodes": snap.episodes if snap else 0,
        "mean_return_last10": snap.mean_return(10) if snap else None,
        "outcomes": snap.outcomes if snap else {},
        "lane_changes": snap.lane_changes if snap else 0,
        "metrics": snap.metrics if snap else {},
        "bridge": bridge,
        "safety": safety,
        "bag": str(bag) if bag.exists() else None,
        "checkpoint": str(ckpt) if ckpt.exists() else None,
        "plots": [str(p) for p in plots],
        "logs": str(run_dir / "logs"),
        "evaluation": evaluation.summary() if evaluation is not None else None,
        "greedy_episode": None if greedy is None else {
            "gif": str(greedy.gif), "bag": str(greedy.bag), "seed": greedy.seed, "steps": greedy.steps,
            "return": greedy.ret, "outcome": greedy.outcome},
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=str))

    console = Console(stderr=False)
    table = Table(title=f"der graph: {outcome.reason}", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    if snap is not None:
        avg = snap.mean_return(10)
        rows = [
            ("scenario / replay", f"{args.scenario} / {_replay_text(params)}"),
            ("decision steps", f"{snap.steps} in {wall:.0f} s"
             + (f" (bridge {bridge['steps_per_s']:.0f}/s once running)" if "steps_per_s" in bridge else "")),
            ("episodes", str(snap.episodes)),
            ("return (mean of last 10)", f"{avg:+.2f}" if avg is not None else "-"),
            ("success / collision / time limit",
             " / ".join(str(snap.outcomes[e]) for e in (EPISODE_SUCCESS, EPISODE_COLLISION, EPISODE_TIME_LIMIT))),
            ("lane changes", str(snap.lane_changes)),
        ]
        if safety is not None:  # der graph --safety: the safety node's count (docs/safety.md)
            rows.append(("safety interventions", f"{int(safety.get('interventions', 0))} of "
                         f"{int(safety.get('commands', 0))} commands vetoed (keep lane instead)" if safety else "-"))
        for name in ("losses/td_loss", "replay/h2_fraction", "charts/epsilon"):
            if name in snap.metrics:
                rows.append((name, f"{snap.metrics[name]:.4g}"))
        if evaluation is not None:
            rows += [
                ("", ""),
                (f"greedy policy ({evaluation.n} held-out episodes)",
                 f"success {evaluation.success_rate:.1%} · caused collisions {evaluation.collision_rate:.1%} · "
                 f"time limit {evaluation.time_limit_rate:.1%}"),
                ("greedy mean return", f"{evaluation.mean_return:+.2f} (the 50-step episode pays ~216 for a safe change)"),
            ]
        for k, v in rows:
            table.add_row(k, v)
    console.print(table)
    # Paths go below the table, one per line and never shortened (a narrow or non-tty console
    # would truncate them inside table cells).
    print(f"  bag:        {summary['bag'] or '-'}")
    print(f"  checkpoint: {summary['checkpoint'] or '-'}")
    for i, plot in enumerate(summary["plots"] or ["-"]):
        print(f"  {'plots:' if i == 0 else '':<11} {plot}")
    if greedy is not None:
        print(f"  episode:    {greedy.gif} ({greedy.describe()})")
    print(f"  logs:       {summary['logs']}")
    if (run_dir / "evaluations.csv").is_file():
        print(f"  evaluation: {run_dir / 'evaluations.csv'}" + (f", {run_dir / 'evaluation.json'}" if evaluation else ""))
    if outcome.ok:
        return 0
    if outcome.reason == "interrupted":
        print("der graph: interrupted; nodes stopped, bag finalised", file=sys.stderr)
        return 130
    print(f"der graph: FAILED: {outcome.describe()}", file=sys.stderr)
    return 1
