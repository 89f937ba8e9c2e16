"""End to end: bridge_node and agent_node as separate processes run a short lockstep training."""

from __future__ import annotations

import json
import re

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from ros_harness import REPO, ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures

from der_ros.nodes import msg_conversions as mc

pytestmark = pytest.mark.ros

PARAMS_FILE = REPO / "config" / "graph.params.yaml"
MAX_STEPS = 150


def bridge_summary(output: str) -> dict:
    match = re.search(r"bridge summary: (\{.*\})", output)
    assert match, f"no summary in the bridge log:\n{output[-3000:]}"
    return json.loads(match.group(1))


def test_bridge_and_agent_train_a_short_episode_sequence(ros_graph, tmp_path):  # noqa: F811
    ckpt = tmp_path / "agent.pt"
    probe = ros_graph.probe
    episodes = probe.collect("episode", DiagnosticArray)
    metrics = probe.collect("agent/metrics", DiagnosticArray)
    agent = ros_graph.start_node(
        "der_ros.nodes.agent_node",
        params_file=PARAMS_FILE,
        params={
            "agent.learning_starts": 32,
            "agent.batch_size": 16,
            "agent.hidden_sizes": [64],
            "agent.epsilon_decay_steps": 100,
            "replay.capacity": 5000,
            "metrics_every": 5,
            "checkpoint_out": str(ckpt),
        },
    )
    bridge = ros_graph.start_node(
        "sumo_bridge.bridge_node",
        params_file=PARAMS_FILE,
        params={"max_steps": MAX_STEPS, "command_timeout": 5.0, "diagnostics_every": 50},
    )
    assert bridge.wait(timeout=90) == 0  # max_steps reached: summary, exit 0
    s = bridge_summary(bridge.output())
    assert s["sim_steps"] == MAX_STEPS
    # lockstep: every simulation step was driven by the agent's own command, none by the timeout
    assert s["commands/accepted"] == MAX_STEPS
    assert s["commands/timeouts"] == 0 and s["commands/late"] == 0 and s["commands/duplicate"] == 0
    assert s["roundtrip_n"] == MAX_STEPS and s["roundtrip_p50_ms"] > 0

    ends = [e for m in list(episodes) for e in mc.parse_episode_events(m) if e[1] != "start"]
    assert len(ends) >= 2 and {e[1] for e in ends} <= {"success", "collision", "time_limit"}
    assert sum(e[2]["steps"] for e in ends) <= MAX_STEPS

    def last_with(key):
        for m in reversed(list(metrics)):
            values = mc.diagnostics_to_metrics(m)
            if key in values:
                return values
        return None

    m = wait_for(lambda: last_with("losses/td_loss"), 20, what="a learning step's metrics", procs=[agent])
    assert m["replay/h2_size"] > 0 and 0.0 <= m["replay/h2_fraction"] <= 1.0
    r = wait_for(lambda: last_with("charts/episodic_return"), 20, what="an episodic return", procs=[agent])
    assert r["charts/episodes"] >= 2
    assert agent.stop() == 0 and ckpt.is_file()
    # the agent stored exactly one transition per simulation step, with no gap
    log = agent.output()
    assert f"stopping (SIGINT): {MAX_STEPS} env steps" in log
    assert f"'transitions': {MAX_STEPS}," in log and "'gaps': 0," in log
