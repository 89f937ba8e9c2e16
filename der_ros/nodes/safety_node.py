"""safety_node: the shield between the agent and the bridge (``der graph --safety rss``; docs/safety.md).

A thin adapter on :class:`der_ros.safety.command_filter.CommandFilter` and
:class:`der_ros.safety.checker.RssChecker`: it reads the same ``state`` as the agent, takes the
agent's command on ``agent/lane_change_cmd`` (the agent's ``lane_change_cmd`` remapped) and
publishes on ``lane_change_cmd`` the command itself or keep lane, with the same stamp, so the
bridge sees one answer per step as before. Every command gets a record on
``safety/interventions`` (the recorder keeps it) and the counts go to ``safety/diagnostics``.

Fails safe: a command whose state is missing, stale (older than ``max_state_age`` or superseded
by a newer state) or unreadable becomes keep lane. The bridge's ``applied_action`` (reward
frame_id) stays the truth the agent learns from: it names what the bridge applied, the filtered
command. Any agent, ours or a user's, can be put behind it: it only has to publish ``Joy`` commands.

``safety.kind: sumo`` is refused here: SUMO's own verdict needs the simulation, which only the
bridge holds (use it in process: ``der train --safety sumo``).
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Joy, PointCloud2

from der_ros.contract import (
    AGENT_COMMAND,
    COMMAND,
    SAFETY_DIAGNOSTICS,
    SAFETY_EVENTS,
    SAFETY_STATUS,
    STATE,
    cloud_to_points,
    command_action,
    header_ns,
    read_state_cdr,
)
from der_ros.contract_ros import topic_qos
from der_ros.nodes import msg_conversions as mc
from der_ros.nodes import node_configs
from der_ros.nodes.node_configs import SafetyNodeConfig
from der_ros.nodes.params import ConfigParameters
from der_ros.nodes.spin import run_node
from der_ros.safety.checker import N_ACTIONS, RssChecker
from der_ros.safety.command_filter import CommandFilter, Decision
from der_ros.safety.config import SafetyConfig
from sumo_bridge.observation import POINT_FIELDS

__all__ = ["SafetyNode", "main", "parameter_sections"]


def parameter_sections() -> dict[str, Any]:
    """Prefix -> default config of every parameter section of this node (for YAML tooling)."""
    return node_configs.parameter_sections("safety_node")


def _allow_all(points: np.ndarray) -> np.ndarray:
    return np.ones(N_ACTIONS, dtype=bool)


class SafetyNode(Node):
    """rclpy adapter around CommandFilter; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("safety_node")
        self.finished = False
        self._params = ConfigParameters(self, parameter_sections())
        self.cfg: SafetyNodeConfig = self._params.get("")
        shield: SafetyConfig = self._params.get("safety")
        if shield.kind == "sumo":
            raise ValueError("safety.kind = 'sumo': SUMO's verdict needs the simulation, which only the bridge holds; "
                             "use 'rss' in the graph (or der train --safety sumo in process)")  # fmt: skip
        mask = RssChecker(shield).mask if shield.kind == "rss" else _allow_all
        if shield.kind == "rss" and shield.beyond_lane:
            self.get_logger().warning("safety.beyond_lane has no effect here: the state carries no lane two away "
                                      "(docs/safety.md, 'The exit scenario')")  # fmt: skip
        self.filter = CommandFilter(mask, max_state_age=self.cfg.max_state_age, max_states=self.cfg.max_states,
                                    max_command_wait=self.cfg.max_command_wait, n_actions=self.cfg.n_actions)  # fmt: skip
        self.sender_id = f"{self.get_fully_qualified_name()}#{os.getpid()}"
        self.pub_cmd = self.create_publisher(Joy, COMMAND, topic_qos(COMMAND))
        self.pub_events = self.create_publisher(DiagnosticArray, SAFETY_EVENTS, topic_qos(SAFETY_EVENTS))
        self.pub_diag = self.create_publisher(DiagnosticArray, SAFETY_DIAGNOSTICS, topic_qos(SAFETY_DIAGNOSTICS))
        self.create_subscription(PointCloud2, STATE, self._on_state, topic_qos(STATE), raw=True)
        self.create_subscription(Joy, AGENT_COMMAND, self._on_command, topic_qos(COMMAND))
        self.bad_states = 0
        self._commands = 0
        # a command that overtook its state waits for it at most max_command_wait (CommandFilter.expire)
        self.create_timer(min(0.02, self.cfg.max_command_wait / 2), self._expire)
        self.get_logger().info(
            f"safety ready: kind={shield.kind} rho={shield.response_time}s accel_max={shield.accel_max} "
            f"brake_min={shield.brake_min} brake_max={shield.brake_max} margin={shield.margin}m"
        )

    def _on_state(self, data: bytes) -> None:
        now = time.monotonic()
        try:
            got = read_state_cdr(data, POINT_FIELDS)
            if got is None:  # another encoding: rclpy decodes it
                msg = deserialize_message(data, PointCloud2)
                got = header_ns(msg), cloud_to_points(msg, POINT_FIELDS)
        except ValueError as exc:  # a point that is not finite, a wrong layout: the stamp's command becomes keep
            self.bad_states += 1
            stamp = self._stamp_of(data)
            if stamp is not None:
                self._publish(self.filter.on_state(stamp, None, now))
            self.get_logger().warning(f"malformed state: {exc}", throttle_duration_sec=1.0)
            return
        except Exception as exc:  # noqa: BLE001 - bytes rclpy cannot decode
            self.bad_states += 1
            self.get_logger().warning(f"undecodable state ({type(exc).__name__})", throttle_duration_sec=1.0)
            return
        stamp, points = got
        self._publish(self.filter.on_state(stamp, points, now))

    @staticmethod
    def _stamp_of(data: bytes) -> int | None:
        try:
            return header_ns(deserialize_message(data, PointCloud2))
        except Exception:  # noqa: BLE001
            return None

    def _on_command(self, msg: Joy) -> None:
        now = time.monotonic()
        stamp = header_ns(msg)
        try:
            action = command_action(msg)
        except ValueError:
            action = -1  # malformed: keep lane
        d = self.filter.command(stamp, action, now)
        if d is not None:
            self._publish([d])

    def _expire(self) -> None:
        self._publish(self.filter.expire(time.monotonic()))

    def _publish(self, decisions: list[Decision]) -> None:
        for d in decisions:
            self.pub_cmd.publish(mc.make_command(d.stamp, d.applied, self.sender_id))
            self.pub_events.publish(mc.make_safety_record(d.stamp, d.verdict, d.proposed, d.applied,
                                                          self.filter.interventions))  # fmt: skip
            self._commands += 1
            if self._commands % self.cfg.diagnostics_every == 0:
                self.publish_diagnostics()

    def summary(self) -> dict[str, float]:
        counts = {f"verdict/{k}": float(v) for k, v in self.filter.counters.items()}
        return {"commands": float(self._commands), "interventions": float(self.filter.interventions),
                "bad_states": float(self.bad_states), **counts}  # fmt: skip

    def publish_diagnostics(self) -> None:
        stamp = int(self.get_clock().now().nanoseconds)
        self.pub_diag.publish(mc.make_diagnostics(stamp, SAFETY_STATUS, self.summary(),
                                                  warn=self.filter.interventions > 0))  # fmt: skip

    def on_shutdown(self, reason: str) -> None:
        self.publish_diagnostics()
        # one JSON line der graph's report reads (der_ros.graph.run_summary.safety_summary)
        self.get_logger().info(f"stopping ({reason}): safety summary: {json.dumps(self.summary())}")


def main(argv: list[str] | None = None) -> int:
    """Console script ``safety_node`` (ROS arguments: ``--ros-args -p name:=value --params-file f``)."""
    return run_node(SafetyNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
