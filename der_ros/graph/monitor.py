"""A small rclpy node inside the ``der graph`` process that watches progress (episodes, steps, metrics).

It runs in its own rclpy Context and a background thread, so the supervisor loop (plain
Python) never blocks on ROS and the monitor never holds the GIL for long: it only counts
``lane_change_cmd`` messages (one per decision step) and parses the rare ``episode`` and
``agent/metrics`` messages.
"""

from __future__ import annotations

import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Joy

from der_ros.contract import (
    COMMAND,
    EPISODE,
    METRICS,
    QosSpec,
    diagnostics_to_metrics,
    parse_episode_events,
    topic_spec,
)
from der_ros.contract_ros import qos_profile
from der_ros.graph.run_progress import ProgressCounter, ProgressSnapshot
from der_ros.nodes.spin import BackgroundNode

__all__ = ["GraphMonitor"]


class GraphMonitor(BackgroundNode):
    """Subscribes to ``lane_change_cmd``, ``episode`` and ``agent/metrics`` in ``domain_id``.

    ``namespace`` is the graph's namespace (topic names are relative to it).
    """

    def __init__(self, domain_id: int, namespace: str = "") -> None:
        self._lock = threading.Lock()
        self._counts = ProgressCounter()  # bounded memory: counters and the recent returns only
        # The runner handles Ctrl-C itself: rclpy must not install its own handlers.
        super().__init__(
            "der_graph_monitor",
            domain_id,
            namespace=namespace or None,
            spin_timeout=0.1,
            thread_name="der-graph-monitor",
            handle_signals=False,
        )
        # the table's QoS with deeper queues: the monitor is a slow reader of bursts
        for name, cls, callback, depth in ((COMMAND, Joy, self._on_cmd, 100), (EPISODE, DiagnosticArray, self._on_episode, 100),
                                           (METRICS, DiagnosticArray, self._on_metrics, 50)):
            spec = topic_spec(name).qos
            qos = qos_profile(QosSpec.make(best_effort=spec.best_effort, depth=max(depth, spec.depth)))
            self.node.create_subscription(cls, name, callback, qos)
        self.start()

    def _on_cmd(self, _msg: Any) -> None:
        with self._lock:
            self._counts.add_step()

    def _on_episode(self, msg: Any) -> None:
        events = parse_episode_events(msg)
        with self._lock:
            for _stamp, event, values in events:
                self._counts.add_event(event, values)

    def _on_metrics(self, msg: Any) -> None:
        metrics = diagnostics_to_metrics(msg)
        with self._lock:
            self._counts.add_metrics(metrics)

    def snapshot(self) -> ProgressSnapshot:
        """A copy of the counters (safe to read from the runner thread)."""
        with self._lock:
            return self._counts.snapshot()
