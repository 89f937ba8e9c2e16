"""SUMO's saved random-number state depends on what ran before in the process: a state saved after
``load`` with the same seed and the same steps carries larger draw counters when another simulation
ran first (libsumo 1.28). The exit scenario's warmed states (sumo_bridge/flow_scenario.py) are saved
this way, so a state cache depends on the order it was filled in (docs/scenarios.md, "Baselines on exit").

    python research/tuning/sumo_rng_counts.py
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import libsumo

from sumo_bridge.network_build import build_scenario_network
from sumo_bridge.scenario_file import load_scenario, shipped_scenario


def main() -> None:
    spec = load_scenario(shipped_scenario("exit"))
    src = spec.network
    net = build_scenario_network("exit", src.net, src.nodes, src.edges, src.connections, spec.demand).net_file

    def args(seed: int) -> list[str]:
        return ["-n", str(net), "-r", ",".join(map(str, spec.demand)), "--step-length", "0.1", "--seed", str(seed),
                "--no-step-log", "true", "--no-warnings", "true", "--save-state.rng", "true"]

    out = Path(tempfile.mkdtemp())
    libsumo.start(["sumo", *args(1)])
    try:
        counters = []
        for k, before in enumerate((0, 300)):  # the same load + 100 steps, after 0 and after 300 other steps
            for _ in range(before):
                libsumo.simulationStep()
            libsumo.load(args(7))
            for _ in range(100):
                libsumo.simulationStep()
            libsumo.simulation.saveState(str(out / f"{k}.xml"))
            counters.append(re.search(r"<rngState default=\"(\d+)\" routeHandler=\"(\d+)\"", (out / f"{k}.xml").read_text()))
    finally:
        libsumo.close()
    for (before, m) in zip((0, 300), counters):
        assert m is not None
        print(f"load(seed 7) + 100 steps after {before:3d} earlier steps: rngState default={m[1]} routeHandler={m[2]}")


if __name__ == "__main__":
    main()
