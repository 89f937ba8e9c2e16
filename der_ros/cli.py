"""The ``der`` command line: one entry point, one subcommand per job.

Each subcommand lives in its own module that defines ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their subcommand runs, so ``der --help``
stays fast and a ROS-free install can still train.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from der_ros import __version__
from der_ros.configuration import ConfigError
from der_ros.interrupts import interrupts_raise

#: name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "train": ("der_ros.train.train_cli", "train a DQN agent (uniform / PER / DER replay) on one environment"),
    "table1": ("der_ros.experiments.table1", "reproduce the paper's Table 1 (CartPole) over several seeds"),
    "table2": ("der_ros.experiments.table2", "run the paper's Table 2 (Atari) protocol"),
    "table3": ("der_ros.experiments.table3", "reproduce the paper's Table 3 (SUMO ring and urban) over several seeds"),
    "baselines": ("der_ros.experiments.baselines", "evaluate the baselines (keep, immediate, gap acceptance, SUMO's model...) or tune gap acceptance"),
    "evaluate": ("der_ros.experiments.evaluate_runs", "re-evaluate trained runs' checkpoints greedily on more evaluation seeds"),
    "sweep": ("der_ros.experiments.sweep", "run a grid of config overrides x seeds (tuning), ranked by greedy evaluation"),
    "graph": ("der_ros.graph.graph_cli", "run the ROS 2 graph: SUMO bridge, DER agent and MCAP recorder"),
    "bag": ("der_ros.offline.bag_cli", "inspect, plot, export, train from, render and play recorded MCAP bags"),
    "bench": ("der_ros.bench_cli", "run a benchmark script from bench/"),
    "networks": ("sumo_bridge.network_cli", "build (or rebuild) the SUMO networks shipped with der_ros"),
}
#: old spelling -> subcommand (``der replay`` was the bag tools' name before issue 42: it read like the
#: replay buffers of ``der_ros.replay``)
ALIASES: dict[str, str] = {"replay": "bag"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="der", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"der_ros {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_module, help_text) in SUBCOMMANDS.items():
        aliases = [old for old, new in ALIASES.items() if new == name]
        sub.add_parser(name, help=help_text, add_help=False, aliases=aliases)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # Parse only up to the subcommand; the subcommand's module builds the rest of its parser.
    top, rest = parser.parse_known_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(top.verbose, 2) if top.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if top.command is None:
        parser.print_help()
        return 2
    top.command = ALIASES.get(top.command, top.command)
    module_name, help_text = SUBCOMMANDS[top.command]
    module = importlib.import_module(module_name)
    sub_parser = argparse.ArgumentParser(prog=f"der {top.command}", description=help_text)
    module.add_arguments(sub_parser)
    args = sub_parser.parse_args(rest)
    try:
        with interrupts_raise():  # SIGINT may arrive ignored (background start): Ctrl-C / SIGTERM must work
            return int(module.run(args) or 0)
    except ConfigError as exc:
        print(f"der {top.command}: configuration error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        if not getattr(exc, "user_facing", False):
            raise
        print(f"der {top.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"der {top.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
