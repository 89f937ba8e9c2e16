"""The nodes' executors: EventsExecutor for the lockstep ends (bridge, agent), overridable for debugging."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from der_ros.configuration import ConfigError
from der_ros.nodes.spin import make_executor

REPO = Path(__file__).resolve().parents[1]


def test_make_executor_kinds_and_override(monkeypatch: pytest.MonkeyPatch) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    monkeypatch.delenv("DER_ROS_EXECUTOR", raising=False)
    rclpy.init()  # the default context (no node: nothing goes on the network)
    try:
        assert isinstance(make_executor("single"), SingleThreadedExecutor)
        events = make_executor("events")
        assert not isinstance(events, SingleThreadedExecutor) and type(events).__name__ == "EventsExecutor"
        monkeypatch.setenv("DER_ROS_EXECUTOR", "single")
        assert isinstance(make_executor("events"), SingleThreadedExecutor)
        monkeypatch.setenv("DER_ROS_EXECUTOR", "threads")
        with pytest.raises(ConfigError, match="DER_ROS_EXECUTOR"):
            make_executor("events")
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize("module, kind", [("bridge_node", "events"), ("agent_node", "events"), ("recorder_node", None)])
def test_each_node_spins_on_its_executor(module: str, kind: str | None) -> None:
    """The bridge and agent ask for the EventsExecutor; the recorder (it reads MessageInfo, which the
    EventsExecutor of rclpy 7.1 cannot pass) keeps the default."""
    tree = ast.parse((REPO / "der_ros" / "nodes" / f"{module}.py").read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "run_node"]
    assert len(calls) == 1
    kinds = [kw.value.value for kw in calls[0].keywords if kw.arg == "executor_kind"]  # type: ignore[attr-defined]
    assert kinds == ([kind] if kind else [])


def test_no_node_on_the_events_executor_takes_message_info() -> None:
    """A two-argument subscription callback (data, MessageInfo) makes rclpy 7.1's EventsExecutor raise
    'SystemError: null argument to internal routine' at the first message."""
    source = (REPO / "der_ros" / "nodes" / "bridge_node.py").read_text()
    tree = ast.parse(source)
    bridge = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "_on_command")
    assert [a.arg for a in bridge.args.args] == ["self", "data"]
