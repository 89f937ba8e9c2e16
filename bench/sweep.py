"""Benchmark: the same sweep on the local backend and on Ray, on this machine's cores (not a test).

The sweep: ``--runs`` short CartPole runs (DQN and DER λ = 0.9 over seeds, ``--steps`` steps each,
the paper's network and batch, TensorBoard off, the config's final greedy evaluation), first with
``--backend local`` (``--jobs`` processes), then with ``--backend ray`` on a Ray instance that the
backend starts on 127.0.0.1 with ``--jobs`` CPUs. Ray's wall time includes starting and stopping
that instance and shipping every run's files (checkpoint included) to the driver: what a user of
``der sweep --backend ray`` waits for. Measured: runs per second of each; ``ray_over_local`` is
their ratio (target >= 0.87, i.e. at most 15% overhead). The two backends' run directories are
also compared (:mod:`der_ros.experiments.run_compare`): ``identical`` says they hold the same
files minus timings. The machine may be shared, so the sweep runs ``--repeats`` times per backend
in the order local, ray, ray, local, ... and the fastest of each counts (least disturbed by other
load), as in ``bench/train.py``. Ends with one JSON line.

    .venv/bin/python bench/sweep.py            # 8 runs x 5,000 steps on 2 processes / 2 Ray CPUs, twice each
    .venv/bin/python bench/sweep.py --quick    # 4 runs x 1,000 steps, once each
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import secrets
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
if "RAY_AUTH_MODE" not in os.environ:  # a token for this run only, not written to ~/.ray (read when ray is imported)
    os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32))

from der_ros.experiments.backends.dispatch import LocalBackend, RayBackend, run_specs  # noqa: E402
from der_ros.experiments.run_compare import run_differences  # noqa: E402
from der_ros.experiments.suite import methods_by_name, plan_runs  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=8, help="runs in the sweep (default 8)")
    parser.add_argument("--steps", type=int, default=5_000, help="environment steps per run (default 5,000)")
    parser.add_argument("--repeats", type=int, default=2, help="sweeps per backend, interleaved; the fastest counts")
    parser.add_argument("--jobs", type=int, default=2, help="local processes = Ray CPUs (default 2)")
    parser.add_argument("--quick", action="store_true", help="4 runs x 1,000 steps")
    args = parser.parse_args()
    if args.quick:
        args.runs, args.steps, args.repeats = 4, 1000, 1
    logging.basicConfig(level=logging.WARNING)
    methods = methods_by_name(["dqn", "der0.9"])
    seeds = list(range(100, 100 + (args.runs + 1) // 2))
    overrides = {"train.total_steps": args.steps, "train.tensorboard": False}
    walls: dict[str, list[float]] = {"local": [], "ray": []}
    order = [("local", "ray")[(r + (r // 2)) % 2] for r in range(2 * args.repeats)]  # local ray ray local ...
    diffs: list[str] = []
    for i, name in enumerate(order):
        with tempfile.TemporaryDirectory(prefix="der-bench-sweep-") as tmp:
            out = Path(tmp) / name
            specs = plan_runs(REPO / "config" / "cartpole.yaml", methods, seeds, out, overrides)[: args.runs]
            backend = LocalBackend(args.jobs) if name == "local" else RayBackend(num_cpus=args.jobs)
            t0 = time.perf_counter()
            run_specs(specs, backend=backend)
            walls[name].append(time.perf_counter() - t0)
            print(f"{name:5s}: {len(specs)} runs in {walls[name][-1]:.1f} s ({len(specs) / walls[name][-1]:.4f} runs/s)",
                  file=sys.stderr, flush=True)  # fmt: skip
            if i == 0:  # keep the first sweep to compare the other backend's with
                reference, first_out = Path(tempfile.mkdtemp(prefix="der-bench-ref-")), out
                shutil.copytree(out, reference / name)
            elif name != order[0] and not diffs and len(walls[name]) == 1:
                for spec in specs:
                    ref = Path(spec.run_dir.replace(str(out), str(reference / order[0])))
                    diffs += run_differences(ref, first_out, spec.run_dir, out)  # paths inside name first_out
    shutil.rmtree(reference, ignore_errors=True)
    wall = {k: min(v) for k, v in walls.items()}
    result = {
        "bench": "sweep",
        "env": "CartPole-v1",
        "runs": args.runs,
        "steps_per_run": args.steps,
        "jobs": args.jobs,
        "local_wall_s": round(wall["local"], 2),
        "ray_wall_s": round(wall["ray"], 2),
        "local_runs_per_s": round(args.runs / wall["local"], 4),
        "ray_runs_per_s": round(args.runs / wall["ray"], 4),
        "ray_over_local": round(wall["local"] / wall["ray"], 3),
        "repeats": args.repeats,
        "local_walls_s": [round(w, 2) for w in walls["local"]],
        "ray_walls_s": [round(w, 2) for w in walls["ray"]],
        "identical": not diffs,
        "load_average_1m": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
