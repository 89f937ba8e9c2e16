"""All the nodes (three, four with the safety node) in one process on one single-threaded executor (``der graph --composed``).

Same nodes, parameters (``--ros-args --params-file``, sections by node name) and topics as the
multi-process graph; messages still go through the middleware, but there are no context
switches between processes and one Python interpreter instead of three (less memory, faster
start-up). The stop order is the same: bridge, agent (checkpoint), recorder (bag) last, after
the executor has drained what is still queued for it.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from der_ros.nodes.agent_node import AgentNode
from der_ros.nodes.bridge_node import BridgeNode
from der_ros.nodes.node_configs import SAFETY_FLAG
from der_ros.nodes.recorder_node import RecorderNode
from der_ros.nodes.safety_node import SafetyNode
from der_ros.nodes.spin import install_stop_handlers

__all__ = ["main"]

log = logging.getLogger("der_graph_composed")


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s")
    args = list(sys.argv if argv is None else argv)
    shielded = SAFETY_FLAG in args  # der graph --safety: the safety node between agent and bridge
    rclpy.init(args=[a for a in args if a != SAFETY_FLAG], signal_handler_options=SignalHandlerOptions.NO)
    stop = install_stop_handlers()
    nodes: list[Any] = []
    classes = (RecorderNode, AgentNode, SafetyNode, BridgeNode) if shielded else (RecorderNode, AgentNode, BridgeNode)
    try:
        for cls in classes:  # recorder first: subscribed before data flows
            nodes.append(cls())
    except (ValueError, RuntimeError) as exc:
        log.error("could not start: %s", exc)
        for node in reversed(nodes):
            node.on_shutdown("start-up failed")
            node.destroy_node()
        rclpy.try_shutdown()
        return 1
    recorder, agent, bridge = nodes[0], nodes[1], nodes[-1]
    safety = nodes[2] if shielded else None
    executor = SingleThreadedExecutor()
    for node in nodes:
        executor.add_node(node)
    log.info("composed graph ready: %s", ", ".join(n.get_name() for n in nodes))
    reason = "finished"
    try:
        while not bridge.finished and not agent.finished and "reason" not in stop:
            executor.spin_once(timeout_sec=0.1)
        reason = stop.get("reason", "finished" if not agent.finished else "agent stopped")
    except (KeyboardInterrupt, ExternalShutdownException):
        reason = "interrupted"
    finally:
        bridge.on_shutdown(reason)
        executor.remove_node(bridge)
        _drain(executor, 0.3)
        agent.on_shutdown(reason)
        executor.remove_node(agent)
        _drain(executor, 0.3)
        if safety is not None:
            safety.on_shutdown(reason)
            executor.remove_node(safety)
        recorder.on_shutdown(reason)
        executor.shutdown(timeout_sec=1.0)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return int(getattr(agent, "exit_code", 0))


def _drain(executor: Any, seconds: float) -> None:
    """Run callbacks still queued (e.g. the last messages for the recorder) for a short while."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)


if __name__ == "__main__":
    sys.exit(main())
