"""A file scenario's warmed traffic state, saved by a fresh process so that it is the same wherever it is made.

Why a fresh process
-------------------
A state saved with ``--save-state.rng`` carries SUMO's random-number generators, and in libsumo 1.28
their draw counters after ``load`` + the same steps with the same seed depend on whatever simulation
ran earlier in the process (``research/tuning/sumo_rng_counts.py``). Saved by the environment that
first needed it, a traffic seed's state therefore depended on the episodes that process had run
before, and a state cache filled in another order (another machine, another suite) continued the
traffic with other random draws. Here the state is made by ``python -m sumo_bridge.traffic_state`` in
a new interpreter that starts SUMO once, runs the warm-up and saves: the file is a function of the
SUMO arguments and the number of steps only. It costs a Python start (~1 s) once per traffic seed;
the cache (:mod:`sumo_bridge.flow_scenario`) keeps it for every later reset.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

__all__ = ["save_warm_state", "state_body"]

#: a state's build takes a Python start, a SUMO start and the warm-up; far longer means something hangs
TIMEOUT_S = 600.0


def save_warm_state(sumo_args: list[str], steps: int, out: str | Path) -> Path:
    """Start SUMO in a fresh process with ``sumo_args``, run ``steps`` steps, save the state to ``out``.

    The file appears whole or not at all (written beside ``out``, then renamed); two processes that
    make the same state write the same content. Raises ``RuntimeError`` with the child's last output.
    """
    if steps < 0:
        raise ValueError(f"steps = {steps}, expected >= 0")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.stem}.{os.getpid()}.tmp.xml")
    job = json.dumps({"args": [str(a) for a in sumo_args], "steps": int(steps), "out": str(tmp)})
    proc = subprocess.run([sys.executable, "-m", __name__, job], capture_output=True, text=True, timeout=TIMEOUT_S)
    if proc.returncode != 0 or not tmp.is_file():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise RuntimeError(f"saving the warmed traffic state {out} failed (rc {proc.returncode}): {' | '.join(tail)}")
    tmp.replace(out)
    return out


def state_body(path: str | Path) -> str:
    """A saved state without SUMO's header comment (it carries the time the file was written)."""
    return re.sub(r"<!--.*?-->", "", Path(path).read_text(), count=1, flags=re.S)


def _main(job: str) -> None:
    import libsumo

    spec = json.loads(job)
    libsumo.start(["sumo", *spec["args"]])
    try:
        for _ in range(spec["steps"]):
            libsumo.simulationStep()
        libsumo.simulation.saveState(spec["out"])
    finally:
        libsumo.close()


if __name__ == "__main__":
    _main(sys.argv[1])
