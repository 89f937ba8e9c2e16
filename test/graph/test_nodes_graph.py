"""End to end: bridge_node and agent_node as separate processes run a short lockstep training."""

from __future__ import annotations

import json
import multiprocessing
import re

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.qos import QoSProfile
from ros_harness import REPO, ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures
from sensor_msgs.msg import PointCloud2

from der_ros import contract as ct

pytestmark = pytest.mark.ros

PARAMS_FILE = REPO / "config" / "graph.params.yaml"
MAX_STEPS = 150
AGENT_OVERRIDES = {
    "agent.learning_starts": 32,
    "agent.batch_size": 16,
    "agent.hidden_sizes": [64],
    "agent.epsilon_decay_steps": 100,
    "replay.capacity": 5000,
}


def reference_episodes(max_steps: int, overrides: dict) -> list[tuple[str, int, float]]:
    """The same training run without ROS: LaneChangeEnv + DQNAgent in one process, calling them in
    the agent node's order (observe, act, then learn; at a terminal state learn, reset, act), with
    the params file's scenario and agent sections. Returns (event, steps, return) per episode."""
    import numpy as np
    import torch
    import yaml

    from der_ros.agent.config import DQNConfig
    from der_ros.agent.dqn import DQNAgent
    from der_ros.configuration import from_dict, unflatten_names
    from der_ros.replay.config import ReplayConfig
    from sumo_bridge.lane_change_env import LaneChangeEnv
    from sumo_bridge.scenario import ScenarioConfig

    torch.set_num_threads(1)
    doc = yaml.safe_load(PARAMS_FILE.read_text())
    bridge = doc["bridge_node"]["ros__parameters"]
    agent_values = {**doc["agent_node"]["ros__parameters"], **overrides}

    def section(values: dict, prefix: str, cls: type) -> object:
        return from_dict(cls, unflatten_names(values, prefix))

    env = LaneChangeEnv(section(bridge, "scenario", ScenarioConfig))
    try:
        obs, _ = env.reset()
        agent = DQNAgent(obs.shape, np.float32, 3, section(agent_values, "agent", DQNConfig),
                         section(agent_values, "replay", ReplayConfig), seed=int(agent_values["seed"]))
        out, ret, length = [], 0.0, 0
        a = agent.act(obs)
        for _ in range(max_steps):
            next_obs, r, term, trunc, info = env.step(a)
            ret += r
            length += 1
            agent.observe(obs, a, r, next_obs, term, trunc)
            if term or trunc:
                out.append((info["event"], length, ret))
                ret, length = 0.0, 0
                agent.learn()
                obs, _ = env.reset()
                a = agent.act(obs)
            else:
                obs = next_obs
                a = agent.act(obs)
                agent.learn()
        return out
    finally:
        env.close()


def bridge_summary(output: str) -> dict:
    match = re.search(r"bridge summary: (\{.*\})", output)
    assert match, f"no summary in the bridge log:\n{output[-3000:]}"
    return json.loads(match.group(1))


def test_bridge_and_agent_train_a_short_episode_sequence(ros_graph, tmp_path):  # noqa: F811
    ckpt = tmp_path / "agent.pt"
    probe = ros_graph.probe
    episodes = probe.collect("episode", DiagnosticArray)
    metrics = probe.collect("agent/metrics", DiagnosticArray)
    # the probe also subscribes to state and reward, and the bridge waits for 2 subscribers (agent +
    # probe) before step 0, so the probe has matched the bridge before the first episode event
    probe.collect("state", PointCloud2, qos=QoSProfile(depth=50))
    probe.collect("reward", Vector3Stamped, qos=QoSProfile(depth=50))
    agent = ros_graph.start_node(
        "der_ros.nodes.agent_node",
        params_file=PARAMS_FILE,
        params={**AGENT_OVERRIDES, "metrics_every": 5, "checkpoint_out": str(ckpt)},
    )
    # the whole run takes well under a second: the probe must know the agent's metrics publisher before
    # it starts, or every metrics message may go out before the two have matched (volatile topic)
    wait_for(lambda: probe.node.count_publishers("agent/metrics") >= 1, 30, what="the agent's metrics publisher",
             procs=[agent])  # fmt: skip
    bridge = ros_graph.start_node(
        "der_ros.nodes.bridge_node",
        params_file=PARAMS_FILE,
        params={"max_steps": MAX_STEPS, "command_timeout": 5.0, "diagnostics_every": 50, "min_subscribers": 2},
    )
    assert bridge.wait(timeout=90) == 0  # max_steps reached: summary, exit 0
    s = bridge_summary(bridge.output())
    assert s["sim_steps"] == MAX_STEPS
    # lockstep: every simulation step was driven by the agent's own command, none by the timeout
    assert s["commands/accepted"] == MAX_STEPS
    assert s["commands/timeouts"] == 0 and s["commands/late"] == 0 and s["commands/duplicate"] == 0
    assert s["roundtrip_n"] == MAX_STEPS and s["roundtrip_p50_ms"] > 0

    n_ends = int(s["events/success"] + s["events/collision"] + s["events/time_limit"])

    def episode_ends():
        found = [e for m in list(episodes) for e in ct.parse_episode_events(m) if e[1] != "start"]
        return found if len(found) == n_ends else None

    ends = wait_for(episode_ends, 10, what=f"{n_ends} episode end events")
    assert len(ends) >= 2 and {e[1] for e in ends} <= {"success", "collision", "time_limit"}
    assert sum(e[2]["steps"] for e in ends) <= MAX_STEPS

    def last_with(key):
        for m in reversed(list(metrics)):
            values = ct.diagnostics_to_metrics(m)
            if key in values:
                return values
        return None

    m = wait_for(lambda: last_with("losses/td_loss"), 20, what="a learning step's metrics", procs=[agent])
    assert m["replay/h2_size"] > 0 and 0.0 <= m["replay/h2_fraction"] <= 1.0
    r = wait_for(lambda: last_with("charts/episodic_return"), 20, what="an episodic return", procs=[agent])
    assert r["charts/episodes"] >= 2
    # the graph reproduces the run without ROS exactly: same episodes, same events, same returns
    with multiprocessing.get_context("spawn").Pool(1) as pool:  # libsumo: one simulation per process
        reference = pool.apply(reference_episodes, (MAX_STEPS, AGENT_OVERRIDES))
    assert [(e[1], e[2]["steps"], e[2]["return"]) for e in ends] == reference

    # the agent stored exactly one transition per simulation step, with no gap
    assert agent.stop() == 0 and ckpt.is_file()
    log = agent.output()
    assert f"stopping (SIGINT): {MAX_STEPS} env steps" in log
    assert f"'transitions': {MAX_STEPS}," in log and "'gaps': 0," in log
    assert "'overridden_actions': 0" in log  # every applied action was the agent's own
