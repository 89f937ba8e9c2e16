"""config/graph.params.yaml stays consistent with the nodes' config dataclasses."""

from __future__ import annotations

import importlib
import typing
from pathlib import Path

import pytest
import yaml

from der_ros.configuration import ConfigError, from_dict, unflatten_names
from der_ros.nodes.params import flat_specs

PARAMS = Path(__file__).resolve().parents[2] / "config" / "graph.params.yaml"
#: node name in the YAML -> module defining parameter_sections()
NODES = {
    "bridge_node": "der_ros.nodes.bridge_node",
    "agent_node": "der_ros.nodes.agent_node",
    "recorder_node": "der_ros.nodes.recorder_node",
    "safety_node": "der_ros.nodes.safety_node",
}
STANDARD = {"use_sim_time"}  # declared by rclpy itself


def _load() -> dict:
    return yaml.safe_load(PARAMS.read_text())


def _sections(node: str) -> dict:
    module = importlib.import_module(NODES[node])
    return module.parameter_sections()


@pytest.mark.parametrize("node", ["bridge_node", "agent_node"])
def test_every_key_is_declared_and_every_value_validates(node):
    values = _load()[node]["ros__parameters"]
    sections = _sections(node)
    owner = {name: prefix for prefix, obj in sections.items() for name in flat_specs(obj, prefix)}
    unknown = sorted(set(values) - set(owner) - STANDARD)
    assert not unknown, f"{PARAMS}: {node} keys that the node does not declare: {unknown}"
    # ROS parameters are statically typed: a float field written as `5` (an integer) would make
    # the node refuse the file at start-up, although the dataclass itself would accept it
    specs = {name: spec for prefix, obj in sections.items() for name, spec in flat_specs(obj, prefix).items()}
    for name, value in values.items():
        if name not in specs or value is None:
            continue
        tp = specs[name].type
        if tp is float:
            assert isinstance(value, float), f"{PARAMS}: {node} {name} = {value!r}: write it as a float (e.g. {value}.0)"
        if typing.get_origin(tp) in (list, tuple) and typing.get_args(tp)[:1] == (float,):
            assert all(isinstance(v, float) for v in value), f"{PARAMS}: {node} {name} = {value!r}: write floats"
    for prefix, obj in sections.items():
        mine = {k: v for k, v in values.items() if owner.get(k) == prefix}
        from_dict(type(obj), unflatten_names(mine, prefix), source=f"{PARAMS} [{node}] {prefix or 'node'}")


def test_other_nodes_in_the_file_are_known():
    doc = _load()
    assert set(doc) <= set(NODES), f"unexpected node sections {set(doc) - set(NODES)}"
    for node in set(doc) - {"bridge_node", "agent_node"}:
        module = importlib.import_module(NODES[node])
        if hasattr(module, "parameter_sections"):
            test_every_key_is_declared_and_every_value_validates(node)


def test_agent_and_bridge_agree():
    doc = _load()
    bridge = doc["bridge_node"]["ros__parameters"]
    agent = doc["agent_node"]["ros__parameters"]
    assert agent["use_sim_time"] is True
    for key, value in agent.items():
        if key.startswith("observation."):
            assert bridge[f"scenario.{key}"] == value, f"agent {key} differs from the bridge's scenario.{key}"
    step = bridge["scenario.step_length"] * bridge["scenario.decision_interval"]
    assert agent["step_seconds"] == pytest.approx(step)


def test_a_bad_value_would_be_caught(tmp_path):
    doc = _load()
    doc["agent_node"]["ros__parameters"]["replay.lam"] = 1.5
    sections = _sections("agent_node")
    values = doc["agent_node"]["ros__parameters"]
    mine = {k: v for k, v in values.items() if k.startswith("replay.")}
    with pytest.raises(ConfigError, match="lam"):
        from_dict(type(sections["replay"]), unflatten_names(mine, "replay"))
