"""What a libsumo ``load()`` leaves behind: RSS per reload of the ring, against resets without one.

The bridge's RSS kept growing in long graph runs after everything of ours was bounded (issue 45,
finding 4). The ring env rebuilds its traffic with ``libsumo.load()`` every ``ring_rebuild_every``
episodes (4 by default) and re-places the warm traffic in between. This measures, in one process
after a warm-up, the RSS (``VmRSS`` after ``malloc_trim``, so freed heap does not count) over

* ``bare_load``: ``libsumo.load()`` of the ring alone, nothing else (SUMO's own cost);
* ``rebuild``: ``env.reset()`` with ``ring_rebuild_every=1`` (a load every reset);
* ``replace``: ``env.reset()`` that never reloads (re-placements only).

Ends with one JSON line: kB per 1,000 calls of each.

    .venv/bin/python bench/sumo_load_rss.py [--calls 600]
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig

_LIBC = ctypes.CDLL("libc.so.6")


def rss_kb() -> int:
    _LIBC.malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def growth(call: Callable[[int], None], calls: int, warmup: int = 50) -> float:
    """kB of RSS per 1,000 calls, after ``warmup`` calls."""
    for i in range(warmup):
        call(i)
    before = rss_kb()
    for i in range(calls):
        call(warmup + i)
    return 1000.0 * (rss_kb() - before) / calls


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=600, help="calls measured per case (default 600)")
    args = ap.parse_args()
    out: dict[str, object] = {"bench": "sumo_load_rss", "calls": args.calls}
    # one libsumo simulation per process: the three cases share the env (its config is swapped)
    ring = ScenarioConfig.ring()
    env = LaneChangeEnv(dataclasses.replace(ring, ring_rebuild_every=1))
    env.reset()
    out["bare_load_kb_per_1000"] = round(growth(lambda i: env.api.load(env._sumo_args(i)), args.calls), 1)
    env.reset()
    out["rebuild_kb_per_1000"] = round(growth(lambda _i: env.reset(), args.calls), 1)
    env.config = dataclasses.replace(ring, ring_rebuild_every=10**9)
    env.reset()
    out["replace_kb_per_1000"] = round(growth(lambda _i: env.reset(), args.calls), 1)
    env.close()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
