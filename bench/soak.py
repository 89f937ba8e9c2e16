"""Soak benchmark: does any process of a long ``der graph`` run keep growing? (issue 45, finding 4)

Runs ``der graph`` for ``--steps`` decision steps (ring, lockstep, the default params file with a
small replay so that it is full early: ``--capacity``) and samples the resident set (VmRSS) of
every process of the run each time the runner prints its progress line (``der graph: step k/N``,
every 10 s): the runner itself, the three nodes (``pids.json``) and the runner's other children
(the greedy evaluation process). Per process, the growth is the least-squares slope of RSS over
decision steps, fitted on the samples after ``--warmup`` steps (replay full, learner warmed up),
in kB per 1,000 steps. Goal: <= 10 kB per 1,000 steps for every process.

Prints a table and ends with one JSON line (per process: samples, rss_first_mb, rss_last_mb,
kb_per_1000_steps). The run directory goes to ``--run-dir`` (default a temporary one, deleted).

    .venv/bin/python bench/soak.py [--steps 20000] [--warmup 5000] [--capacity 2000] [--run-dir DIR] [-p NODE:NAME=VALUE]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_STEP = re.compile(r"der graph: step (\d+)/(\d+)")


def rss_kb(pid: int) -> int | None:
    """VmRSS of ``pid`` in kB (None once it has exited)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return None


def children(pid: int) -> list[int]:
    """Direct children of ``pid`` (every thread's list)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError):
            continue
    return out


def processes(runner: int, run_dir: Path) -> dict[str, int]:
    """name -> pid of every process of the run: runner, nodes, and the runner's other children."""
    procs = {"runner": runner}
    try:
        nodes = json.loads((run_dir / "pids.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        nodes = {}
    procs.update({str(k): int(v) for k, v in nodes.items()})
    known = set(procs.values())
    for pid in sorted(c for c in children(runner) if c not in known):
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except (FileNotFoundError, ProcessLookupError):
            continue
        # multiprocessing's resource tracker, and the spawned greedy evaluation worker
        procs["resource_tracker" if "resource_tracker" in argv else f"evaluation_{pid}"] = pid
    return procs


def slope_per_1000(points: list[tuple[int, int]]) -> float | None:
    """Least-squares slope of (step, kB) points, in kB per 1,000 steps (None with < 3 points)."""
    if len(points) < 3:
        return None
    n = len(points)
    mx = sum(p[0] for p in points) / n
    my = sum(p[1] for p in points) / n
    sxx = sum((p[0] - mx) ** 2 for p in points)
    if sxx == 0:
        return None
    sxy = sum((p[0] - mx) * (p[1] - my) for p in points)
    return 1000.0 * sxy / sxx


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20000, help="decision steps of the graph run (default 20000)")
    ap.add_argument("--warmup", type=int, default=5000, help="steps left out of the fit (default 5000)")
    ap.add_argument("--capacity", type=int, default=2000, help="replay capacity: full after this many steps")
    ap.add_argument("--run-dir", type=Path, default=None, help="keep the run here (default: a temporary dir)")
    ap.add_argument("-p", "--param", action="append", default=[], metavar="NODE:NAME=VALUE",
                    help="extra der graph parameter (repeatable), e.g. bridge_node:scenario.ring_rebuild_every=1000000")
    args = ap.parse_args(argv)
    if args.warmup >= args.steps:
        raise SystemExit(f"--warmup = {args.warmup} must be below --steps = {args.steps}")

    tmp = None
    if args.run_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="der_soak_")
        run_dir = Path(tmp.name) / "run"
    else:
        run_dir = args.run_dir.resolve()
    cmd = [sys.executable, "-m", "der_ros.cli", "graph", "--steps", str(args.steps), "--run-dir", str(run_dir),
           "--no-plots", "--no-gif", "--eval-interval", "5000", "--eval-episodes", "10", "--final-eval-episodes", "0",
           "-p", f"agent_node:replay.capacity={args.capacity}", *(a for p in args.param for a in ("-p", p))]
    print("soak: " + " ".join(cmd), file=sys.stderr, flush=True)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    samples: dict[str, list[tuple[int, int]]] = {}
    tail: list[str] = []

    def read_stderr() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            tail.append(line)
            del tail[:-30]
            m = _STEP.search(line)
            if m is None:
                continue
            step = int(m.group(1))
            for name, pid in processes(proc.pid, run_dir).items():
                kb = rss_kb(pid)
                if kb is not None:
                    samples.setdefault(name, []).append((step, kb))

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    rc = proc.wait()
    reader.join(timeout=10)
    wall = time.monotonic() - t0
    if rc != 0:
        print("".join(tail), file=sys.stderr)
        print(f"soak: der graph exited {rc}", file=sys.stderr)
        return 1

    result: dict[str, object] = {"bench": "soak", "steps": args.steps, "warmup": args.warmup,
                                 "replay_capacity": args.capacity, "params": args.param, "wall_s": round(wall, 1),
                                 "processes": {}}
    rows = []
    for name, pts in sorted(samples.items()):
        name = "evaluation" if name.startswith("evaluation_") else name
        fit = [p for p in pts if p[0] >= args.warmup]
        slope = slope_per_1000(fit)
        entry = {"samples": len(fit), "rss_first_mb": round(pts[0][1] / 1024, 1), "rss_last_mb": round(pts[-1][1] / 1024, 1),
                 "kb_per_1000_steps": None if slope is None else round(slope, 1)}
        result["processes"][name] = entry  # type: ignore[index]
        rows.append((name, entry))
    print(f"{'process':<16} {'samples':>7} {'RSS first MB':>12} {'RSS last MB':>11} {'kB / 1000 steps':>15}")
    for name, e in rows:
        slope_txt = "-" if e["kb_per_1000_steps"] is None else f"{e['kb_per_1000_steps']:+.1f}"
        print(f"{name:<16} {e['samples']:>7} {e['rss_first_mb']:>12} {e['rss_last_mb']:>11} {slope_txt:>15}")
    print(json.dumps(result))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
