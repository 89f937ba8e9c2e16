"""``der graph``: run the SUMO bridge, the DER agent and the MCAP recorder as one supervised ROS 2 graph.

Each node runs in its own process (``python -m <module> --ros-args --params-file
<run_dir>/params.yaml``) in a private ROS domain with discovery limited to this host. The
per-run choices (scenario, steps, replay kind, lambda, seeds, output paths) are merged into a
copy of the params YAML written to the run directory, so a run can be repeated exactly with
the node executables alone.

Order: recorder first (so it is subscribed before any data flows), then agent, then bridge; the
bridge waits for the agent, runs ``--steps`` decision steps and exits 0, after which the agent
is stopped (it saves its checkpoint) and the recorder last (it finalises the bag). Then the trained
agent is evaluated greedily (:mod:`der_ros.graph.snapshot_evaluation`) and one greedy episode is recorded
and rendered to ``plots/greedy_episode.gif`` (:mod:`der_ros.graph.greedy_episode`). Ctrl-C does
the same stop sequence at any time. If a node dies, the others are stopped and ``der graph``
exits 1 naming the node and showing the end of its log.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import yaml

from der_ros.configuration import ConfigError
from der_ros.contract import AGENT_COMMAND, COMMAND
from der_ros.graph.greedy_episode import greedy_episode_gif
from der_ros.graph.preflight import check_graph_files, writable_problem
from der_ros.graph.run_progress import Progress
from der_ros.graph.run_summary import bridge_summary, report, safety_summary, snapshot_from_bag, unanswered_run
from der_ros.graph.snapshot_evaluation import GraphEvaluator, graph_safety_config
from der_ros.graph.supervisor import (
    ChildFailed,
    ProcessSpec,
    RunOutcome,
    Supervisor,
    reserve_domain_id,
    ros_environment,
)
from der_ros.interrupts import interrupts_raise
from der_ros.nodes.node_configs import SAFETY_FLAG
from der_ros.nodes.params import build_graph_params, load_params_file, parse_overrides

__all__ = ["add_arguments", "run", "node_specs", "default_params_file", "NODES"]

log = logging.getLogger("der.graph")

#: node name -> (python module, readiness log line)
NODES: dict[str, tuple[str, str]] = {
    "recorder_node": ("der_ros.nodes.recorder_node", r"recorder ready"),
    "agent_node": ("der_ros.nodes.agent_node", r"agent ready"),
    "safety_node": ("der_ros.nodes.safety_node", r"safety ready"),
    "bridge_node": ("der_ros.nodes.bridge_node", r"bridge ready"),
}
#: the safety node starts before the agent: it is the subscriber of the agent's (remapped) command that the
#: agent's start-up gate (min_command_subscribers) waits for; started after, the agent waited out its 30 s timeout
START_ORDER = ("recorder_node", "safety_node", "agent_node", "bridge_node")
#: outputs der graph places in the run directory (unless -p sets them)
RUN_DIR_OUTPUTS = {("recorder_node", "output"), ("agent_node", "checkpoint_out"), ("agent_node", "policy_dir")}
STOP_ORDER = ("bridge_node", "agent_node", "safety_node", "recorder_node")
#: ``der graph --safety`` choices; the default is the shield on (docs/safety.md, "Why the graph runs it by default")
GRAPH_SAFETY = ("rss", "none")
DEFAULT_SAFETY = "rss"
#: the agent's command goes to the safety node instead of the bridge (a ROS remapping of the agent node only)
AGENT_REMAP = f"agent_node:{COMMAND}:={AGENT_COMMAND}"


def default_params_file() -> Path | None:
    """``config/graph.params.yaml`` of the source tree, else of an installed package's share dir."""
    here = Path(__file__).resolve().parents[2] / "config" / "graph.params.yaml"
    if here.is_file():
        return here
    share = Path(sys.prefix) / "share" / "der_ros" / "config" / "graph.params.yaml"
    return share if share.is_file() else None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="ring",
                        help="ring, urban (built in), exit (shipped) or the path of a scenario file (docs/scenarios.md); "
                        "default ring")
    parser.add_argument("--steps", type=int, default=15000,
                        help="decision steps the bridge simulates before the run ends (default 15000, the paper's "
                        "training length: a few minutes on 2 cores)")
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
    parser.add_argument("--eval-interval", type=int, default=2500,
                        help="greedy evaluation of the agent's policy every this many steps, in a second process on "
                        "held-out seeds (default 2500, as config/ring.yaml; 0 = only the final one)")
    parser.add_argument("--eval-episodes", type=int, default=50, help="episodes per periodic evaluation (default 50)")
    parser.add_argument("--final-eval-episodes", type=int, default=300,
                        help="episodes of the evaluation of the trained agent at the end (default 300; 0 = none)")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG plots nor the greedy episode GIF")
    parser.add_argument("--no-gif", action="store_true",
                        help="do not record and render the greedy episode GIF at the end (plots/greedy_episode.gif)")
    parser.add_argument("--safety", default=DEFAULT_SAFETY, metavar="{rss,sumo,none}",
                        help="the shield between agent and bridge (a safety_node; docs/safety.md): rss (default) or "
                        "none; sumo is refused here, SUMO's verdict needs the simulation only the bridge holds (use "
                        "der train --safety sumo in process)")
    parser.add_argument("--grace", type=float, default=20.0,
                        help="seconds each node gets to stop after SIGINT before SIGTERM/SIGKILL (default 20)")


def node_specs(params_path: Path, env: dict[str, str], composed: bool, safety: str = "none") -> list[ProcessSpec]:
    """The processes of the graph, in start order (the safety node only with ``safety`` other than none)."""
    ros_args = ["--ros-args", "--params-file", str(params_path)]
    shielded = safety != "none"
    if shielded:
        ros_args += ["-r", AGENT_REMAP]
    if composed:
        flag = [SAFETY_FLAG] if shielded else []
        return [ProcessSpec("graph", [sys.executable, "-m", "der_ros.graph.composed", *flag, *ros_args], env,
                            ready_pattern=r"composed graph ready", ready_timeout=120, finishes_run=True)]
    return [
        ProcessSpec(name, [sys.executable, "-m", NODES[name][0], *ros_args], env, ready_pattern=NODES[name][1],
                    ready_timeout=120, finishes_run=name == "bridge_node")
        for name in START_ORDER if shielded or name != "safety_node"
    ]


def check_safety(value: str) -> str:
    """``--safety``'s value, or a one-line ConfigError (before anything is written or started)."""
    if value == "sumo":
        raise ConfigError("--safety = 'sumo': not in the graph (SUMO's verdict needs the simulation, which only the "
                          "bridge holds); use rss or none, or der train/table3 --safety sumo in process")  # fmt: skip
    if value not in GRAPH_SAFETY:
        raise ConfigError(f"--safety = {value!r}, expected one of rss, none (sumo: in process only)")
    return value


def run(args: argparse.Namespace) -> int:
    """One ``der graph`` run. Expects SIGINT and SIGTERM to raise KeyboardInterrupt (``der`` and
    :func:`main` install that: a background start would otherwise inherit SIGINT ignored)."""
    safety = check_safety(args.safety)
    if args.steps < 1:  # a bad input: exit 2 like every other (ConfigError), before anything starts
        raise ConfigError(f"--steps = {args.steps}, expected >= 1")
    for flag, value in (("--eval-interval", args.eval_interval), ("--eval-episodes", args.eval_episodes),
                        ("--final-eval-episodes", args.final_eval_episodes)):  # fmt: skip
        if value < 0:
            raise ConfigError(f"{flag} = {value}, expected >= 0")
    run_dir = args.run_dir or Path("runs") / time.strftime("graph-%Y%m%d-%H%M%S", time.gmtime())
    if run_dir.exists() and any(run_dir.iterdir()):
        raise SystemExit(f"der graph: run directory {run_dir} exists and is not empty")
    run_dir = run_dir.resolve()
    params_in = args.params if args.params is not None else default_params_file()
    params = build_graph_params(  # checks every node's parameters (one line per error) before any output
        load_params_file(params_in), steps=args.steps, scenario=args.scenario, run_dir=run_dir,
        free_run=args.free_run, replay=args.replay, lam=args.lam, seed=args.seed, overrides=args.param,
        base_name=str(params_in) if params_in is not None else "node defaults", safety=safety)
    evaluating = bool(args.eval_interval and args.eval_episodes) or bool(args.final_eval_episodes)
    if args.eval_interval and args.eval_episodes:
        params["agent_node"]["ros__parameters"]["policy_every"] = int(args.eval_interval)
        params["agent_node"]["ros__parameters"]["policy_dir"] = str(run_dir / "policies")
    overridden = parse_overrides(args.param)
    base_origin = str(params_in) if params_in is not None else "node defaults"

    def origin_of(node: str, name: str) -> str:
        if name in overridden.get(node, {}):
            return "-p"
        return "--run-dir" if (node, name) in RUN_DIR_OUTPUTS else base_origin

    problem = writable_problem(run_dir, "new_dir")
    if problem is not None:
        raise ConfigError(f"--run-dir {run_dir}: {problem}")
    check_graph_files(params, origin_of)  # files and paths the nodes will use: one line, before any process starts
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
    evaluator = GraphEvaluator(run_dir, params, run_dir / "policies", args.eval_episodes if args.eval_interval else 0,
                               args.final_eval_episodes, shielded=safety != "none") if evaluating else None  # fmt: skip
    outcome: RunOutcome | None = None
    t0 = time.monotonic()
    try:
        from der_ros.graph.monitor import GraphMonitor  # lazy: rclpy (``der graph --help`` stays fast)

        monitor = GraphMonitor(lease.domain_id)
        try:
            sup.start_all(node_specs(params_path, env, args.composed, safety))
        except ChildFailed as exc:
            outcome = sup.finish(RunOutcome(False, f"{exc.name} failed to start", failed=exc.name))
        except KeyboardInterrupt:
            outcome = sup.finish(RunOutcome(False, "interrupted"))
        else:
            for name, proc in sup.procs.items():
                print(f"der graph: {name} pid {proc.pid}", file=sys.stderr, flush=True)
            progress = Progress(args.steps)

            def tick() -> None:
                snap = monitor.snapshot()
                line = snap.line()
                last = evaluator.poll() if evaluator is not None else None
                if last is not None:
                    line += f" | greedy@{last.step}: success {last.success_rate:.0%}, collisions {last.collision_rate:.0%}"
                progress.update(snap.steps, line)

            outcome = sup.supervise(on_tick=tick, poll_interval=0.25)
    finally:
        if outcome is None:  # an unexpected error: never leave nodes behind
            sup.stop_all()
        if progress is not None:
            progress.close()
        snap = monitor.snapshot() if monitor is not None else None
        if monitor is not None:
            monitor.close()
        lease.release()
    assert outcome is not None  # set on every path that does not raise
    wall = time.monotonic() - t0
    snap = snapshot_from_bag(run_dir / "bag", snap)
    bridge = bridge_summary(run_dir / "logs")
    shield = safety_summary(run_dir / "logs") if safety != "none" else None
    outcome = unanswered_run(outcome, bridge)  # every node exited 0 but the agent answered nothing: a failure
    if snap is not None and "sim_steps" in bridge:
        snap.steps = int(bridge["sim_steps"])  # the bridge's own count of simulated decision steps
    final = None
    if evaluator is not None:
        try:
            if outcome.ok and args.final_eval_episodes:
                print(f"der graph: evaluating the trained agent greedily on {args.final_eval_episodes} held-out episodes "
                      "...", file=sys.stderr, flush=True)  # fmt: skip
            final = evaluator.finish(run_dir / "agent.pt" if outcome.ok else None)
        except (RuntimeError, OSError, KeyError) as exc:  # an evaluation must not turn a finished run into a failure
            log.warning("greedy evaluation failed: %s", exc)
        finally:
            evaluator.close()
    greedy = None
    if outcome.ok and not (args.no_plots or args.no_gif) and (run_dir / "agent.pt").is_file():
        print("der graph: recording and rendering one greedy episode of the trained agent ...", file=sys.stderr,
              flush=True)  # fmt: skip
        greedy = greedy_episode_gif(run_dir, run_dir / "agent.pt", params,
                                    shield=graph_safety_config(params) if safety != "none" else None)
    return report(outcome, snap, run_dir, wall, args, params, bridge, final, greedy, shield)


def main(argv: list[str] | None = None) -> int:
    """``python -m der_ros.graph.graph_cli`` (same as ``der graph``)."""
    parser = argparse.ArgumentParser(prog="der graph", description=__doc__.splitlines()[0])
    add_arguments(parser)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    with interrupts_raise():
        return run(parser.parse_args(argv))


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
