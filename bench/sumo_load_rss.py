"""What a libsumo ``load()`` leaves behind: RSS per rebuild of the ring, for each way of rebuilding.

The bridge's RSS kept growing in long graph runs after everything of ours was bounded (issue 45,
finding 4). The ring env rebuilds its traffic with ``libsumo.load()`` every ``ring_rebuild_every``
episodes (4 by default) and re-places the warm traffic in between. This measures, in one process
after ``--warmup`` calls of each case, the RSS growth (``VmRSS``, read after ``malloc_trim`` so that
freed heap does not count, unless the case says otherwise) over ``--calls`` calls of

* ``bare_load``: ``libsumo.load()`` of the ring with the env's arguments, nothing else;
* ``bare_restart``: ``libsumo.close()`` + ``libsumo.start()`` instead of ``load()``;
* ``bare_load_no_trim``: ``bare_load``, RSS read without ``malloc_trim`` (what trimming gives back);
* ``bare_load_no_validation``: ``bare_load`` with ``--xml-validation[.net|.routes] never`` (no schemas);
* ``bare_load_relative_paths``: ``bare_load`` with the net and route files named relative to the
  working directory (``ring.net.xml`` instead of a ~60-character absolute path);
* ``bare_load_net_only``: ``bare_load`` without the route file (one input file fewer);
* ``rebuild``: ``env.reset()`` with ``ring_rebuild_every=1`` (a load at every reset);
* ``replace``: ``env.reset()`` that never reloads (re-placements only).

Ends with one JSON line: kB per 1,000 calls of each case (``<case>_kb_per_1000``) and the mean
milliseconds per call (``<case>_ms``).

    .venv/bin/python bench/sumo_load_rss.py [--calls 600] [--warmup 50] [--cases bare_load,bare_restart]

Where the memory goes (``bare_load`` under valgrind; the growth of "definitely lost" between two call
counts is what one load leaks; ``--trace-children`` follows the ROS wheels' re-exec of python)::

    PYTHONMALLOC=malloc valgrind --trace-children=yes --leak-check=full --num-callers=30 \\
        --log-file=vg.%p.txt .venv/bin/python bench/sumo_load_rss.py --cases bare_load --warmup 0 --calls 20
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig

_LIBC = ctypes.CDLL("libc.so.6")
_NO_VALIDATION = ["--xml-validation", "never", "--xml-validation.net", "never", "--xml-validation.routes", "never"]
CASES = (
    "bare_load",
    "bare_restart",
    "bare_load_no_trim",
    "bare_load_no_validation",
    "bare_load_relative_paths",
    "bare_load_net_only",
    "rebuild",
    "replace",
)


def rss_kb(trim: bool = True) -> int:
    if trim:
        _LIBC.malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def growth(call: Callable[[int], None], calls: int, warmup: int, trim: bool = True) -> tuple[float, float]:
    """(kB of RSS per 1,000 calls after ``warmup`` calls, mean ms per call)."""
    for i in range(warmup):
        call(i)
    before = rss_kb(trim)
    t0 = time.perf_counter()
    for i in range(calls):
        call(warmup + i)
    ms = 1000.0 * (time.perf_counter() - t0) / calls
    return 1000.0 * (rss_kb(trim) - before) / calls, ms


def _option(args: list[str], flag: str) -> int:
    return args.index(flag) + 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=600, help="calls measured per case (default 600)")
    ap.add_argument("--warmup", type=int, default=50, help="calls of each case before its measurement (default 50)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {','.join(CASES)}")
    args = ap.parse_args()
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown or args.calls < 1 or args.warmup < 0:
        ap.error(f"--cases {unknown} unknown (choose from {CASES})" if unknown else "--calls >= 1, --warmup >= 0")
    out: dict[str, object] = {"bench": "sumo_load_rss", "calls": args.calls, "warmup": args.warmup}
    # one libsumo simulation per process: every case shares the env (its config is swapped)
    ring = ScenarioConfig.ring()
    env = LaneChangeEnv(dataclasses.replace(ring, ring_rebuild_every=1))
    env.reset()
    api: Any = env.api

    def sumo_args(i: int) -> list[str]:
        return env._sumo_args(i)

    def load(i: int) -> None:
        api.load(sumo_args(i))

    def restart(i: int) -> None:
        api.close()
        api.start(["sumo", *sumo_args(i)])

    def load_no_validation(i: int) -> None:
        api.load(sumo_args(i) + _NO_VALIDATION)

    def load_relative(i: int) -> None:
        a = sumo_args(i)
        for flag in ("-n", "-r"):
            a[_option(a, flag)] = Path(a[_option(a, flag)]).name
        api.load(a)

    def load_net_only(i: int) -> None:
        a = sumo_args(i)
        k = a.index("-r")
        api.load(a[:k] + a[k + 2 :])

    calls: dict[str, tuple[Callable[[int], None], bool]] = {
        "bare_load": (load, True),
        "bare_restart": (restart, True),
        "bare_load_no_trim": (load, False),
        "bare_load_no_validation": (load_no_validation, True),
        "bare_load_relative_paths": (load_relative, True),
        "bare_load_net_only": (load_net_only, True),
    }
    cwd = os.getcwd()
    for case in cases:
        if case in calls:
            call, trim = calls[case]
            if case == "bare_load_relative_paths":
                os.chdir(env.network.net_file.parent)
            try:
                kb, ms = growth(call, args.calls, args.warmup, trim)
            finally:
                os.chdir(cwd)
        else:
            env.config = dataclasses.replace(ring, ring_rebuild_every=1 if case == "rebuild" else 10**9)
            env.reset(seed=0)  # a load, whatever the previous case left
            kb, ms = growth(lambda _i: env.reset(), args.calls, args.warmup)
        out[f"{case}_kb_per_1000"] = round(kb, 1)
        out[f"{case}_ms"] = round(ms, 2)
        print(f"{case:26s} {kb:8.1f} kB per 1,000 calls  {ms:6.2f} ms per call", flush=True)
    env.close()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
