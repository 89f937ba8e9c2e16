"""``der networks``: build (or rebuild) the SUMO networks shipped with der_ros.

Networks are otherwise built on first use; this command builds them ahead of time (e.g. in a
Docker image or before parallel runs) and prints where they are and their lane layout.
"""

from __future__ import annotations

import argparse
import logging

from sumo_bridge.network_build import (
    NETWORK_NAMES,
    NetworkBuildError,
    SumoNotFoundError,
    build_network,
    netconvert_version,
)

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"networks to build (default: all of {', '.join(NETWORK_NAMES)})")  # fmt: skip
    parser.add_argument("--force", action="store_true", help="rebuild even if the cached build is up to date")


def _summary(net_file: str) -> str:
    import sumolib

    net = sumolib.net.readNet(net_file)
    edges = [e for e in net.getEdges() if not e.getID().startswith(":")]
    lanes = sorted({e.getLaneNumber() for e in edges})
    total = sum(e.getLength() for e in edges)
    return f"{len(edges)} edges, lanes per edge {lanes}, {total:.0f} m of road"


def run(args: argparse.Namespace) -> int:
    names = args.names or list(NETWORK_NAMES)
    for name in names:
        if name not in NETWORK_NAMES:
            print(f"der networks: unknown network {name!r}; expected one of {', '.join(NETWORK_NAMES)}")
            return 2
    try:
        print(f"netconvert: {netconvert_version()}")
        for name in names:
            built = build_network(name, force=args.force)
            print(f"{name}: {built.net_file} ({_summary(str(built.net_file))}); routes {built.route_file}")
    except (SumoNotFoundError, NetworkBuildError) as exc:
        print(f"der networks: {exc}")
        return 1
    return 0
