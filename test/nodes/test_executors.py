"""The nodes' executors: EventsExecutor for the lockstep ends (bridge, agent), overridable for debugging."""

from __future__ import annotations

import ast
import time
from pathlib import Path

import pytest
from ros_harness import ros_domain  # noqa: F401 (fixture)

from der_ros.configuration import ConfigError
from der_ros.nodes.spin import make_executor

REPO = Path(__file__).resolve().parents[2]


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


@pytest.mark.parametrize("mode", ["lockstep", "free_run"])
def test_the_command_path_starts_and_steps_the_bridge_when_its_timers_are_late(ros_domain: int, mode: str) -> None:  # noqa: F811
    """A flood of commands can delay the EventsExecutor's timers without bound (its event queue is FIFO):
    the bridge then never ran its start-up check (test_adversarial's flood test, under load). Here no
    executor spins at all, so no timer ever fires, and stray commands alone must start the run and step
    it: by the free-run tick, or in lockstep by the timeout checked at each command."""
    import rclpy
    from rclpy.serialization import serialize_message

    from der_ros.nodes import msg_conversions as mc
    from der_ros.nodes.bridge_node import BridgeNode

    params = {"mode": mode, "wait_for_agent": 0.2, "command_timeout": 0.1, "real_time_factor": 5.0, "markers": False}
    args = ["--ros-args"] + [a for k, v in params.items() for a in ("-p", f"{k}:={str(v).lower()}")]
    rclpy.init(args=args, domain_id=ros_domain)
    try:
        node = BridgeNode()
        try:
            stray = serialize_message(mc.make_command(10**9, 1, "stray-commander"))
            deadline = time.monotonic() + 20.0
            while node.sim_steps < 3 and time.monotonic() < deadline:
                node._on_command(stray)
                time.sleep(0.02)
            assert node.episode >= 0, "the run never started"
            assert node.sim_steps >= 3
        finally:
            node.env.close()
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
