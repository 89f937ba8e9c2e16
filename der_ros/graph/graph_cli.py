"""``der graph``: run the SUMO bridge, the DER agent and the MCAP recorder as one supervised ROS 2 graph.

Each node runs in its own process (``python -m <module> --ros-args --params-file
<run_dir>/params.yaml``) in a private ROS domain with discovery limited to this host. The
per-run choices (scenario, steps, replay kind, lambda, seeds, output paths) are merged into a
copy of the params YAML written to the run directory, so a run can be repeated exactly with
the node executables alone.

Order: recorder first (so it is subscribed before any data flows), then agent, then bridge; the
bridge waits for the agent, runs ``--steps`` decision steps and exits 0, after which the agent
is stopped (it saves its checkpoint) and the recorder last (it finalises the bag). Ctrl-C does
the same stop sequence at any time. If a node dies, the others are stopped and ``der graph``
exits 1 naming the node and showing the end of its log.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import re
import signal
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from der_ros.bag.writer import read_episode_summary
from der_ros.contract import COMMAND, EPISODE_START, STATE, default_record_topics
from der_ros.graph.monitor import ProgressSnapshot
from der_ros.graph.runner import ChildFailed, ProcessSpec, RunOutcome, Supervisor, reserve_domain_id, ros_environment

__all__ = ["add_arguments", "run", "build_params", "node_specs", "default_params_file", "NODES"]

log = logging.getLogger("der.graph")

#: node name -> (python module, readiness log line)
NODES: dict[str, tuple[str, str]] = {
    "recorder_node": ("der_ros.nodes.recorder_node", r"recorder ready"),
    "agent_node": ("der_ros.nodes.agent_node", r"agent ready"),
    "bridge_node": ("der_ros.nodes.bridge_node", r"bridge ready"),
}
START_ORDER = ("recorder_node", "agent_node", "bridge_node")
STOP_ORDER = ("bridge_node", "agent_node", "recorder_node")


def default_params_file() -> Path | None:
    """``config/graph.params.yaml`` of the source tree, else of an installed package's share dir."""
    here = Path(__file__).resolve().parents[2] / "config" / "graph.params.yaml"
    if here.is_file():
        return here
    share = Path(sys.prefix) / "share" / "der_ros" / "config" / "graph.params.yaml"
    return share if share.is_file() else None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", choices=("ring", "urban"), default="ring", help="SUMO network (default ring)")
    parser.add_argument("--steps", type=int, default=5000,
                        help="decision steps the bridge simulates before the run ends (default 5000, about a "
                        "minute on 2 cores)")
    parser.add_argument("--params", type=Path, default=None,
                        help="ROS params YAML (default: config/graph.params.yaml of der_ros)")
    parser.add_argument("--run-dir", type=Path, default=None, help="output directory (default runs/graph-<UTC time>)")
    parser.add_argument("--replay", choices=("uniform", "per", "der"), default=None,
                        help="replay kind of the agent (default: the params file's, else der)")
    parser.add_argument("--lam", type=float, default=None, help="DER lambda (replay.lam)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the agent and of the scenario")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS_DOMAIN_ID of the graph (default: a free one in 1..101)")
    parser.add_argument("--free-run", action="store_true",
                        help="bridge steps on a timer (real_time_factor) instead of waiting for each command")
    parser.add_argument("--composed", action="store_true",
                        help="run the three nodes in one process with one executor (less IPC, one log)")
    parser.add_argument("-p", "--param", action="append", default=[], metavar="NODE:NAME=VALUE",
                        help="extra parameter, e.g. agent_node:agent.lr=0.001 (value parsed as YAML); repeatable")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG plots at the end")
    parser.add_argument("--grace", type=float, default=20.0,
                        help="seconds each node gets to stop after SIGINT before SIGTERM/SIGKILL (default 20)")


def _parse_extra(items: list[str]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        node, sep, rest = item.partition(":")
        name, eq, value = rest.partition("=")
        if not sep or not eq or node not in NODES or not name:
            raise SystemExit(f"der graph: --param {item!r}: expected NODE:NAME=VALUE with NODE in {', '.join(NODES)}")
        out.setdefault(node, {})[name] = yaml.safe_load(value)
    return out


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested parameter maps as dotted names (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``), as ROS reads them."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        name = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(flatten(v, name))
        else:
            out[name] = v
    return out


def build_params(base: dict[str, Any], args: argparse.Namespace, run_dir: Path) -> dict[str, Any]:
    """The params YAML of this run: ``base`` plus the command-line choices (node-name sections).

    Parameters are written with flat dotted names so a command-line value replaces the file's
    value whether the file nested it or not.
    """
    params = copy.deepcopy(base) if base else {}
    for node in NODES:
        section = params.setdefault(node, {})
        if not isinstance(section, dict) or not isinstance(section.get("ros__parameters", {}), dict):
            raise SystemExit(f"der graph: params section {node!r} is not a mapping with ros__parameters")
        section["ros__parameters"] = flatten(section.get("ros__parameters") or {})

    def put(node: str, name: str, value: Any) -> None:
        params[node]["ros__parameters"][name] = value

    put("bridge_node", "max_steps", int(args.steps))

    put("bridge_node", "scenario.network", args.scenario)
    if args.free_run:
        put("bridge_node", "mode", "free_run")
    if args.replay is not None:
        put("agent_node", "replay.kind", args.replay)
    if args.lam is not None:
        put("agent_node", "replay.lam", float(args.lam))
    if args.seed is not None:
        put("agent_node", "seed", int(args.seed))
        put("bridge_node", "scenario.seed", int(args.seed))
    put("agent_node", "checkpoint_out", str(run_dir / "agent.pt"))
    put("recorder_node", "output", str(run_dir / "bag"))
    extra = _parse_extra(args.param)
    for node, values in extra.items():
        for name, value in values.items():
            put(node, name, _typed(node, name, value))
    rec = params["recorder_node"]["ros__parameters"]
    records_state = rec.get("all_topics") or STATE in [
        str(t).lstrip("/") for t in rec.get("topics", default_record_topics())]
    if records_state and "min_subscribers" not in extra.get("bridge_node", {}):
        # the bridge waits for agent + recorder: else a fast run can step before the recorder matched it
        put("bridge_node", "min_subscribers", 2)
    return params


def _typed(node: str, name: str, value: Any) -> Any:
    """A ``-p`` value with the parameter's declared type (``20`` -> ``20.0`` for a float parameter)."""
    import importlib

    from der_ros.nodes.params import flat_specs

    module = importlib.import_module(NODES[node][0])
    specs = {k: v for prefix, obj in module.parameter_sections().items() for k, v in flat_specs(obj, prefix).items()}
    if name == "use_sim_time":
        return bool(value)
    if name not in specs:
        raise SystemExit(f"der graph: --param {node}:{name}: {node} has no parameter {name!r}; "
                         f"known: {', '.join(sorted(specs))}")
    if specs[name].type is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if specs[name].type is str and not isinstance(value, str):
        return str(value)
    return value


def node_specs(params_path: Path, env: dict[str, str], composed: bool) -> list[ProcessSpec]:
    """The processes of the graph, in start order."""
    ros_args = ["--ros-args", "--params-file", str(params_path)]
    if composed:
        return [ProcessSpec("graph", [sys.executable, "-m", "der_ros.graph.composed", *ros_args], env,
                            ready_pattern=r"composed graph ready", ready_timeout=120, finishes_run=True)]
    return [
        ProcessSpec(name, [sys.executable, "-m", NODES[name][0], *ros_args], env, ready_pattern=NODES[name][1],
                    ready_timeout=120, finishes_run=name == "bridge_node")
        for name in START_ORDER
    ]


def _load_base(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    if not path.is_file():
        raise SystemExit(f"der graph: params file {path} not found")
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise SystemExit(f"der graph: {path}: expected a mapping of node names")
    return data


class _Progress:
    """On a terminal: a rich progress bar with a status line under it (log lines go above);
    otherwise a plain status line every 10 s."""

    def __init__(self, total: int) -> None:
        self.total = total
        self._last_line = 0.0
        self._live: Any = None
        self._handlers: list[tuple[logging.Handler, Any]] = []
        if sys.stderr.isatty():
            from rich.console import Console, Group
            from rich.live import Live
            from rich.logging import RichHandler
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
            from rich.text import Text

            console = Console(stderr=True)
            self._progress = Progress(TextColumn("[bold]decision steps"), BarColumn(), MofNCompleteColumn(),
                                      TimeElapsedColumn(), console=console)
            self._task = self._progress.add_task("graph", total=total)
            self._status = Text("waiting for the first episode", overflow="fold")
            self._live = Live(Group(self._progress, self._status), console=console, refresh_per_second=4)
            root = logging.getLogger()
            for h in list(root.handlers):  # route log records through rich so they print above the bar
                root.removeHandler(h)
                self._handlers.append((h, None))
            self._rich_handler = RichHandler(console=console, show_path=False)
            root.addHandler(self._rich_handler)
            self._live.start()

    def update(self, steps: int, status: str) -> None:
        if self._live is not None:
            self._progress.update(self._task, completed=min(steps, self.total))
            self._status.plain = status
        elif time.monotonic() - self._last_line > 10.0:
            self._last_line = time.monotonic()
            print(f"der graph: step {steps}/{self.total} | {status}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()
            root = logging.getLogger()
            root.removeHandler(self._rich_handler)
            for h, _ in self._handlers:
                root.addHandler(h)
            self._live = None


def _fallback_plot(returns: list[float], out_dir: Path) -> list[Path]:
    """Episode returns with a moving average (used when the bag tools cannot plot)."""
    if not returns:
        return []
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    import numpy as np

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
        from der_ros.bag.plots import plot_bags

        written = plot_bags([bag], out_dir)
        if written:
            return list(written)
    except Exception as exc:  # plotting must not turn a finished run into a failure
        log.warning("bag plots failed (%s); plotting the monitored returns instead", exc)
    return _fallback_plot(returns, out_dir)


def _term_as_interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    if args.steps < 1:
        raise SystemExit("der graph: --steps must be >= 1")
    run_dir = args.run_dir or Path("runs") / time.strftime("graph-%Y%m%d-%H%M%S", time.gmtime())
    if run_dir.exists() and any(run_dir.iterdir()):
        raise SystemExit(f"der graph: run directory {run_dir} exists and is not empty")
    run_dir = run_dir.resolve()
    params_in = args.params if args.params is not None else default_params_file()
    params = build_params(_load_base(params_in), args, run_dir)  # rejects bad --param before any output
    run_dir.mkdir(parents=True, exist_ok=True)
    params_path = run_dir / "params.yaml"
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))

    lease = reserve_domain_id(args.domain_id)
    env = ros_environment(lease.domain_id)
    sup = Supervisor(run_dir, stop_order=STOP_ORDER, grace_int=args.grace, grace_term=5.0, cwd=Path.cwd())
    print(f"der graph: run dir {run_dir}, ROS_DOMAIN_ID={lease.domain_id}, params {params_in or '(node defaults)'}",
          file=sys.stderr, flush=True)
    monitor = None
    progress = None
    outcome: RunOutcome | None = None
    t0 = time.monotonic()
    old_term = signal.signal(signal.SIGTERM, _term_as_interrupt)  # SIGTERM = Ctrl-C: stop in order
    try:
        from der_ros.graph.monitor import GraphMonitor  # imports rclpy

        monitor = GraphMonitor(lease.domain_id)
        try:
            sup.start_all(node_specs(params_path, env, args.composed))
        except ChildFailed as exc:
            outcome = sup.finish(RunOutcome(False, f"{exc.name} failed to start", failed=exc.name))
        except KeyboardInterrupt:
            outcome = sup.finish(RunOutcome(False, "interrupted"))
        else:
            for name, proc in sup.procs.items():
                print(f"der graph: {name} pid {proc.pid}", file=sys.stderr, flush=True)
            progress = _Progress(args.steps)

            def tick() -> None:
                snap = monitor.snapshot()
                progress.update(snap.steps, snap.line())

            outcome = sup.supervise(on_tick=tick, poll_interval=0.25)
    finally:
        if outcome is None:  # an unexpected error: never leave nodes behind
            sup.stop_all()
        signal.signal(signal.SIGTERM, old_term)
        if progress is not None:
            progress.close()
        snap = monitor.snapshot() if monitor is not None else None
        if monitor is not None:
            monitor.close()
        lease.release()
    assert outcome is not None  # set on every path that does not raise
    wall = time.monotonic() - t0
    snap = _snapshot_from_bag(run_dir / "bag", snap)
    bridge = _bridge_summary(run_dir / "logs")
    if snap is not None and "sim_steps" in bridge:
        snap.steps = int(bridge["sim_steps"])  # the bridge's own count of simulated decision steps
    return _report(outcome, snap, run_dir, wall, args, params, bridge)


def _bridge_summary(log_dir: Path) -> dict[str, float]:
    """The JSON summary line the bridge logs when it stops ({} if absent)."""
    for name in ("bridge_node.log", "graph.log"):
        path = log_dir / name
        if path.is_file():
            found = re.findall(r"bridge summary: (\{.*\})", path.read_text(errors="replace"))
            if found:
                try:
                    return dict(json.loads(found[-1]))
                except json.JSONDecodeError:
                    return {}
    return {}


def _snapshot_from_bag(bag: Path, live: ProgressSnapshot | None) -> ProgressSnapshot | None:
    """Final counts from the recorded bag (complete: the recorder stopped last), not the live monitor.

    The monitor only sees what arrives after its own discovery finished, so a short run can start
    before it matched the bridge; the bag's episode summary and topic counts have everything.
    """
    if not (bag / "metadata.yaml").is_file():
        return live
    try:
        events = read_episode_summary(bag)
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        counts = {t["topic_metadata"]["name"]: int(t["message_count"]) for t in meta["topics_with_message_count"]}
    except (OSError, KeyError, TypeError, yaml.YAMLError) as exc:
        log.warning("could not read the bag summary (%s); using the live counts", exc)
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


def _report(outcome: RunOutcome, snap: Any, run_dir: Path, wall: float, args: argparse.Namespace,
            params: dict[str, Any], bridge: dict[str, float]) -> int:
    from rich.console import Console
    from rich.table import Table

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
        "bag": str(bag) if bag.exists() else None,
        "checkpoint": str(ckpt) if ckpt.exists() else None,
        "plots": [str(p) for p in plots],
        "logs": str(run_dir / "logs"),
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
             f"{snap.outcomes['success']} / {snap.outcomes['collision']} / {snap.outcomes['time_limit']}"),
            ("lane changes", str(snap.lane_changes)),
        ]
        for name in ("losses/td_loss", "replay/h2_fraction", "charts/epsilon"):
            if name in snap.metrics:
                rows.append((name, f"{snap.metrics[name]:.4g}"))
        for k, v in rows:
            table.add_row(k, v)
    console.print(table)
    # Paths go below the table, one per line and never shortened (a narrow or non-tty console
    # would truncate them inside table cells).
    print(f"  bag:        {summary['bag'] or '-'}")
    print(f"  checkpoint: {summary['checkpoint'] or '-'}")
    for i, plot in enumerate(summary["plots"] or ["-"]):
        print(f"  {'plots:' if i == 0 else '':<11} {plot}")
    print(f"  logs:       {summary['logs']}")
    if outcome.ok:
        return 0
    if outcome.reason == "interrupted":
        print("der graph: interrupted; nodes stopped, bag finalised", file=sys.stderr)
        return 130
    print(f"der graph: FAILED: {outcome.describe()}", file=sys.stderr)
    return 1


def main(argv: list[str] | None = None) -> int:
    """``python -m der_ros.graph.graph_cli`` (same as ``der graph``)."""
    parser = argparse.ArgumentParser(prog="der graph", description=__doc__.splitlines()[0])
    add_arguments(parser)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
