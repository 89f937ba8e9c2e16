"""Benchmark: how many lockstep steps the agent's answers still drive under a lane_change_cmd flood.

Runs bridge_node + agent_node (the params file's settings, lockstep) for ``--steps`` steps while
0..``--max-flooders`` extra processes publish commands on ``lane_change_cmd`` as fast as Python can
(random stamps, actions 0..4). Two kinds of flood:

* ``stray``: the flooders use their own sender id (a stray commander, a test tool left running):
  the bridge drops them by sender before decoding them;
* ``spoofed``: the flooders copy the agent's sender id (a deliberate attacker on the loopback
  graph): every one is decoded and judged in full (the gate still rejects them: their stamps are
  not the open step's).

Prints, per run, the bridge's counters: accepted (steps driven by the agent's answer), timeouts,
late answers, commands rejected and the flood rate the bridge absorbed. On the bridge of before
(KEEP_LAST 10, one executor round trip per message) one stray flooder left 33-45 of 100 steps to
the agent on the loaded 2-core development machine. Ends with one JSON line.

    .venv/bin/python bench/command_flood.py [--steps 200] [--max-flooders 2] [--timeout 2.0]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARAMS_FILE = REPO / "config" / "graph.params.yaml"

FLOODER = r"""
import sys
import numpy as np
import rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Joy
from der_ros.nodes import msg_conversions as mc

rclpy.init()
node = rclpy.create_node("flooder_" + sys.argv[1])
pub = node.create_publisher(Joy, "lane_change_cmd", QoSProfile(depth=10))
rng = np.random.default_rng(int(sys.argv[1]))
sender = sys.argv[2]
msgs = [mc.make_command(int(rng.integers(0, 10**12)), int(rng.integers(0, 5)), sender) for _ in range(997)]
print("flooding", flush=True)
i = 0
while True:
    pub.publish(msgs[i % len(msgs)])
    i += 1
"""

REJECTIONS = ("foreign_sender", "unknown_step", "malformed", "out_of_range", "late", "duplicate")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def run(steps: int, flooders: int, kind: str, timeout: float, workdir: Path) -> dict:
    """One graph run under ``flooders`` flooders of ``kind``; the bridge's counters."""
    from der_ros.graph.supervisor import reserve_domain_id, ros_environment

    lease = reserve_domain_id()
    env = ros_environment(lease.domain_id)
    tag = f"{kind}{flooders}"
    procs: list[subprocess.Popen] = []
    try:
        agent_log = workdir / f"agent_{tag}.log"
        with open(agent_log, "wb") as fh:
            procs.append(subprocess.Popen([sys.executable, "-m", "der_ros.nodes.agent_node", "--ros-args", "--params-file",
                                           str(PARAMS_FILE)], cwd=REPO, env=env, stdout=fh, stderr=subprocess.STDOUT,
                                          start_new_session=True))  # fmt: skip
        deadline = time.monotonic() + 120
        while "agent ready" not in agent_log.read_text():
            if time.monotonic() > deadline or procs[0].poll() is not None:
                raise RuntimeError(f"agent did not start:\n{agent_log.read_text()[-2000:]}")
            time.sleep(0.1)
        sender = re.search(r"sender id (\S+)", agent_log.read_text()).group(1) if kind == "spoofed" else "stray"
        for i in range(flooders):
            procs.append(subprocess.Popen([sys.executable, "-c", FLOODER, str(i), sender], cwd=REPO, env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                          start_new_session=True))  # fmt: skip
        time.sleep(2.0 if flooders else 0.0)
        t0 = time.monotonic()
        bridge = subprocess.run([sys.executable, "-m", "der_ros.nodes.bridge_node", "--ros-args", "--params-file",
                                 str(PARAMS_FILE), "-p", f"max_steps:={steps}", "-p", f"command_timeout:={timeout}"],
                                cwd=REPO, env=env, capture_output=True, text=True, timeout=120 + steps * timeout)  # fmt: skip
        wall = time.monotonic() - t0
        match = re.search(r"bridge summary: (\{.*\})", bridge.stdout + bridge.stderr)
        if match is None:
            raise RuntimeError(f"no bridge summary:\n{(bridge.stdout + bridge.stderr)[-3000:]}")
        s = json.loads(match.group(1))
        rejected = int(sum(s[f"commands/{k}"] for k in REJECTIONS))
        return {"kind": kind, "flooders": flooders, "steps": steps, "accepted": int(s["commands/accepted"]),
                "timeouts": int(s["commands/timeouts"]), "late": int(s["commands/late"]), "rejected": rejected,
                "flood_per_s": round(rejected / max(wall, 1e-9)), "wall_s": round(wall, 1)}  # fmt: skip
    finally:
        for p in reversed(procs):
            _stop(p)
        lease.release()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="lockstep steps per run (default 200)")
    parser.add_argument("--max-flooders", type=int, default=2, help="runs with 0..N flooder processes (default 2)")
    parser.add_argument("--timeout", type=float, default=2.0, help="the bridge's command_timeout (default 2.0 s)")
    parser.add_argument("--quick", action="store_true", help="50 steps, one flooder")
    args = parser.parse_args()
    steps, top = (50, 1) if args.quick else (args.steps, args.max_flooders)
    workdir = Path(tempfile.mkdtemp(prefix="der_bench_flood_"))
    rows = [run(steps, 0, "stray", args.timeout, workdir)]
    for kind in ("stray", "spoofed"):
        rows += [run(steps, n, kind, args.timeout, workdir) for n in range(1, top + 1)]
    print(f"{'flood':>10} {'procs':>5} {'accepted':>9} {'timeouts':>9} {'late':>5} {'rejected':>9} {'flood/s':>8}",
          file=sys.stderr)  # fmt: skip
    for r in rows:
        print(f"{r['kind'] if r['flooders'] else 'none':>10} {r['flooders']:>5} {r['accepted']:>5}/{r['steps']:<3} "
              f"{r['timeouts']:>9} {r['late']:>5} {r['rejected']:>9} {r['flood_per_s']:>8}", file=sys.stderr)  # fmt: skip
    print(json.dumps({"bench": "command_flood", "runs": rows, "logs": str(workdir)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
