"""A user's scenario file in the ROS graph: bridge_node and agent_node on test/scenarios/tiny with its
five actions (the parameters `der graph --scenario PATH` writes), a short lockstep training."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml
from ros_harness import REPO, ros_domain, ros_graph  # noqa: F401 - fixtures

from der_ros.nodes.params import build_graph_params, load_params_file

pytestmark = pytest.mark.ros

TINY = REPO / "test" / "scenarios" / "tiny" / "tiny.yaml"
MAX_STEPS = 120


def test_graph_runs_a_scenario_file_with_speed_actions(ros_graph, tmp_path: Path) -> None:  # noqa: F811
    params = build_graph_params(load_params_file(REPO / "config" / "graph.params.yaml"), steps=MAX_STEPS,
                                scenario=str(TINY), run_dir=tmp_path, seed=3)  # fmt: skip
    agent_params = params["agent_node"]["ros__parameters"]
    agent_params.update({"agent.learning_starts": 32, "agent.batch_size": 16, "agent.hidden_sizes": [32],
                         "agent.epsilon_decay_steps": 60, "replay.capacity": 2000, "replay.h2_capacity": 320})  # fmt: skip
    assert agent_params["n_actions"] == 5
    params["recorder_node"]["ros__parameters"]["output"] = str(tmp_path / "bag")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    ros_graph.start_node("der_ros.nodes.agent_node", params_file=path)
    bridge = ros_graph.start_node("der_ros.nodes.bridge_node", params_file=path,
                                  params={"command_timeout": 10.0, "min_subscribers": 1})  # fmt: skip
    assert bridge.wait(timeout=240) == 0
    match = re.search(r"bridge summary: (\{.*\})", bridge.output())
    assert match, bridge.output()[-3000:]
    s = json.loads(match.group(1))
    assert s["sim_steps"] == MAX_STEPS
    # every step driven by the agent's own command: actions 3 and 4 are accepted, not out of range
    assert s["commands/accepted"] == MAX_STEPS and s["commands/out_of_range"] == 0
    ends = {k[len("events/"):]: v for k, v in s.items() if k.startswith("events/") and v > 0}
    assert ends and set(ends) <= {"success", "collision", "time_limit", "missed"}
