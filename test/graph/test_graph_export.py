"""Offline export = what the online agent stored, on a real graph run with forced command timeouts.

The bridge applies its default action (0, keep lane) when the agent's command misses
``command_timeout``, and names the applied action in the next reward; the agent stores the
applied action. Here the timeout is 2 ms and the test freezes the agent's process
(SIGSTOP ... SIGCONT, 10 ms every 30 ms) while the bridge steps, so commands arrive late
whatever the machine's speed: the agent answers the states that queued up meanwhile after the
bridge has applied its default. (A checkpoint every 10 steps also pauses the agent, but on a
fast disk such a save can take less than the timeout: CI once saw no overridden action.)
``der bag export`` of the recorded bag must give exactly the transitions in the agent's
replay: same observations (bit for bit), the applied actions, rewards, flags, in the same order.
"""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np
from ros_harness import *  # noqa: F403 - ros_domain fixture
from test_graph_cli import der_graph, node_logs, reap

from der_ros.agent.dqn import DQNAgent
from der_ros.bag.reader import BagReader
from der_ros.offline.export import build_transitions


def freeze_agent_now_and_then(run_dir: Path, done: threading.Event, pause: float = 0.010,
                              every: float = 0.030) -> threading.Thread:
    """A thread that stops the agent's process for ``pause`` s every ``every`` s until ``done``."""

    def run() -> None:
        pids = run_dir / "pids.json"
        pid = None
        while pid is None and not done.is_set():
            try:
                pid = json.loads(pids.read_text()).get("agent_node")
            except (OSError, ValueError):  # not written yet, or half written
                pass
            if pid is None:
                time.sleep(0.02)  # never a busy loop beside the nodes starting up
        while pid is not None and not done.is_set():
            try:
                os.kill(pid, signal.SIGSTOP)
                try:
                    time.sleep(pause)
                finally:
                    os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                return
            time.sleep(every)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_export_equals_the_agents_replay_after_timeouts(ros_domain: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    proc = der_graph(
        run_dir, ros_domain, "--steps", "150", "--seed", "5", "--no-plots",
        "--safety", "none",  # agent -> bridge directly: a second hop made every answer miss the 2 ms under load
        "-p", "bridge_node:command_timeout=0.002",
        "-p", "agent_node:replay.kind=uniform", "-p", "agent_node:replay.capacity=10000",
        "-p", "agent_node:agent.learning_starts=100000",  # no gradient steps: the agent stays quick
        "-p", "agent_node:checkpoint_every=10",  # ... except for these pauses and the test's freezes
        "-p", "agent_node:warm_up=false",
    )
    done = threading.Event()
    freezer = freeze_agent_now_and_then(run_dir, done)
    try:
        out, _ = proc.communicate(timeout=180)
    finally:
        done.set()
        freezer.join(timeout=5)
        reap(proc, run_dir)
    assert proc.returncode == 0, out + node_logs(run_dir)
    bridge = json.loads(re.search(r"bridge summary: (\{.*\})", (run_dir / "logs" / "bridge_node.log").read_text())[1])
    assert bridge["commands/late"] > 0, bridge  # the forced timeouts happened, and their commands came late

    agent = DQNAgent.load(run_dir / "agent.pt")
    n = len(agent.replay)
    stored = agent.replay.storage.gather(np.arange(n, dtype=np.int64))  # uniform ring, capacity > n: in order
    tr = build_transitions(BagReader(run_dir / "bag"))

    recorder_log = (run_dir / "logs" / "recorder_node.log").read_text()
    closed = re.findall(r"bag closed: .*", recorder_log)
    counters = re.findall(r"counters .*", (run_dir / "logs" / "agent_node.log").read_text())  # gaps: agent-side loss
    assert len(tr) == n > 100, (len(tr), n, tr.skipped, bridge, closed, counters)  # what to look at if it ever differs
    obs, actions, rewards, next_obs, terminated, truncated = stored
    assert np.array_equal(tr.obs, obs) and np.array_equal(tr.next_obs, next_obs)
    assert np.array_equal(tr.actions, actions)
    assert np.array_equal(tr.rewards.astype(np.float32), rewards)
    assert np.array_equal(tr.terminated, terminated) and np.array_equal(tr.truncated, truncated)
    # the commanded action differed from the applied one somewhere: exporting commands would have failed
    assert tr.overridden > 0, (bridge, counters)
