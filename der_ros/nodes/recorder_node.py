"""recorder_node: records the graph's topics into a rosbag2 MCAP bag (thin rclpy adapter).

The bag is written by the ROS-free :class:`der_ros.bag.writer.BagWriter`; this node only
subscribes, stamps and hands over bytes:

* Subscriptions are ``raw=True``: the middleware hands over the CDR bytes, which go to the
  bag unchanged (no deserialise/serialise round trip, and any message type can be recorded).
* Topics: the ``topics`` parameter (default: the graph's table, :mod:`der_ros.contract`), whose
  types come from the table or, for other names, from graph discovery; with ``all_topics`` every
  topic that shows up in the graph (rescanned every ``discovery_period`` s) except
  ``exclude_topics``; ``record_scene: false`` leaves out the scene marker topics. A topic's
  subscription QoS: best effort if the table or any publisher says so (a reliable reader would
  not match a best-effort writer), transient-local if the table says so (``scene/road``, published
  once: the recorder gets it whenever it joins) or every publisher is, KEEP_LAST ``queue_depth``.
* Offered QoS written into the bag: the publishers' QoS from ``get_publishers_info_by_topic``
  when the topic's first message arrives (the table's QoS if no publisher is known then).
* Stamps: MCAP log_time = receive time on this node's clock (system time; sim time if the node
  runs with ``use_sim_time``), publish_time = the middleware's system receive timestamp.
  rosbag2 uses system receive time by default; with ``use_sim_time: false`` (our default) both
  are system time. The sim-time step key of every message is in its header stamp.
* ``/tf``: for every ``ego/odom`` message recorded, the ``map -> ego`` transform of its pose
  (same stamp and log time) is written on ``/tf`` (tf2_msgs/TFMessage), so that viewers placing
  frames from tf (Foxglove's 3D panel) can put the ``state`` cloud (frame ``ego``) in the scene
  (frame ``map``). Written by the recorder because no node publishes tf (the tf2_msgs package is
  not a dependency; rosbags knows the type).
* Durability of the bag: the writer flushes every ``flush_every_messages`` messages and a timer
  calls ``maybe_flush`` so at most ``flush_every_seconds`` of data can be lost to a SIGKILL;
  SIGINT/SIGTERM finalise the bag (footer, summary, metadata.yaml counts).
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.node import Node

from der_ros.bag.recorder_config import RecorderConfig, default_bag_path
from der_ros.bag.writer import BagWriter, BagWriterError, jazzy_typestore
from der_ros.contract import (
    ODOM,
    SCENE_TOPICS,
    TF,
    TF_MSGTYPE,
    TF_QOS,
    QosSpec,
    read_odometry_pose_cdr,
    tf_cdr,
    topic_by_name,
)
from der_ros.contract_ros import message_class, qos_profile, qos_to_rosbag2
from der_ros.nodes.params import ConfigParameters
from der_ros.nodes.spin import run_node

__all__ = ["RecorderNode", "main", "parameter_sections"]

log = logging.getLogger("recorder_node")


def parameter_sections() -> dict[str, Any]:
    """Prefix -> default config of every parameter section of this node (for YAML tooling)."""
    return {"": RecorderConfig()}


def _is_scene(topic: str) -> bool:
    """A scene marker topic of the contract (``record_scene`` decides whether it is recorded)."""
    spec = topic_by_name(topic)
    return spec is not None and spec.name in SCENE_TOPICS


class RecorderNode(Node):
    """Subscribes to the configured / discovered topics and writes them to a :class:`BagWriter`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("recorder_node", **kwargs)
        self._bound = ConfigParameters(self, parameter_sections())
        cfg: RecorderConfig = self._bound.get("")
        self.cfg = cfg
        out = Path(cfg.output) if cfg.output else default_bag_path()
        use_sim = bool(self.get_parameter("use_sim_time").value)
        self.writer = BagWriter(
            out,
            flush_every_messages=cfg.flush_every_messages,
            flush_every_seconds=cfg.flush_every_seconds,
            compression=None if cfg.compression == "none" else cfg.compression,
            max_file_messages=cfg.max_bag_messages or None,
            max_file_bytes=cfg.max_bag_size or None,
            custom_data={
                "der_ros/recorder": self.get_fully_qualified_name(),
                "der_ros/log_time": "receive time, " + ("ROS sim time" if use_sim else "system time"),
                "der_ros/publish_time": "receive time, system time",
            },
        )
        self._subs: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self._skipped: set[str] = set()
        self._excluded = {self.resolve_topic_name(t) for t in cfg.exclude_topics}
        self._wanted = [self.resolve_topic_name(t) for t in cfg.topics if cfg.record_scene or not _is_scene(t)]
        self._received = 0
        self._odom = self.resolve_topic_name(ODOM)  # its poses also go to /tf (map -> ego)
        self.finished = False  # the recorder runs until signalled (run_node protocol)
        for name in self._wanted:
            spec = topic_by_name(name)
            if spec is not None and name.endswith(spec.name.lstrip("/")):
                self._subscribe(name, spec.msgtype, best_effort=spec.qos.best_effort,
                                transient_local=spec.qos.transient_local)
        self._discover()
        self.create_timer(cfg.discovery_period, self._discover)
        self.create_timer(min(0.25, cfg.flush_every_seconds / 2), self.writer.maybe_flush)
        self.get_logger().info(
            f"recorder ready: recording {len(self._subs)} topics to {self.writer.path}"
            + (" (+ every discovered topic)" if cfg.all_topics else "")
        )

    # -- subscriptions -----------------------------------------------------------------
    def _publisher_qos(self, topic: str) -> list[dict[str, Any]]:
        """The QoS the publishers of ``topic`` offer, as rosbag2 dicts (what the bag stores)."""
        try:
            return [qos_to_rosbag2(info.qos_profile) for info in self.get_publishers_info_by_topic(topic)]
        except Exception:  # graph query during shutdown
            return []

    def _subscribe(self, topic: str, msgtype: str, best_effort: bool = False, transient_local: bool = False) -> None:
        if topic in self._subs or topic in self._skipped:
            return
        cls = message_class(msgtype)
        if cls is None or msgtype not in jazzy_typestore().fielddefs:
            self._skipped.add(topic)
            self.get_logger().warning(
                f"not recording {topic}: message type {msgtype} is not installed or not in the Jazzy typestore"
            )
            return
        pubs = [QosSpec.from_rosbag2(q) for q in self._publisher_qos(topic)]
        best_effort = best_effort or any(q.best_effort for q in pubs)
        transient = transient_local or (bool(pubs) and all(q.transient_local for q in pubs))
        qos = qos_profile(QosSpec.make(best_effort=best_effort, transient_local=transient, depth=self.cfg.queue_depth))

        def on_message(data: bytes, info: Any, topic: str = topic, msgtype: str = msgtype) -> None:
            self._on_message(topic, msgtype, data, info)

        self._subs[topic] = self.create_subscription(cls, topic, on_message, qos, raw=True)
        self._types[topic] = msgtype
        self.get_logger().debug(f"subscribed to {topic} [{msgtype}] ({'best effort' if best_effort else 'reliable'})")

    def _discover(self) -> None:
        try:
            graph = dict(self.get_topic_names_and_types())
        except Exception:  # context shutting down
            return
        for name in self._wanted:
            if name not in self._subs and name in graph and graph[name]:
                self._subscribe(name, graph[name][0])
        if self.cfg.all_topics:
            for name, types in graph.items():
                if name not in self._subs and name not in self._excluded and types:
                    self._subscribe(name, types[0])

    # -- recording ---------------------------------------------------------------------
    def _on_message(self, topic: str, msgtype: str, data: bytes, info: Any) -> None:
        now = self.get_clock().now().nanoseconds
        if not self.writer.has_topic(topic):
            offered = self._publisher_qos(topic)
            try:
                self.writer.add_topic(topic, msgtype, offered or None)
            except BagWriterError as exc:
                self.get_logger().error(f"cannot record {topic}: {exc}")
                self.destroy_subscription(self._subs.pop(topic))
                self._skipped.add(topic)
                return
        received = info.get("received_timestamp") if isinstance(info, dict) else None
        published = int(received or time.time_ns())
        self.writer.write(topic, now, data, publish_time_ns=published)
        self._received += 1
        if topic == self._odom:
            self._write_tf(now, published, data)

    def _write_tf(self, log_time: int, publish_time: int, odom: bytes) -> None:
        """The ``map -> ego`` transform of an ``ego/odom`` message on ``/tf`` (module docstring)."""
        pose = read_odometry_pose_cdr(odom)
        if pose is None:  # not little-endian plain CDR: no transform for this one
            return
        stamp, frame, child, p = pose
        if not self.writer.has_topic(TF):
            self.writer.add_topic(TF, TF_MSGTYPE, TF_QOS)
        self.writer.write(TF, log_time, tf_cdr(stamp, p[:3], p[3:], frame, child), publish_time_ns=publish_time)

    @property
    def subscribed_topics(self) -> dict[str, str]:
        return dict(self._types)

    def on_shutdown(self, reason: str) -> None:
        """Called by :func:`run_node` with ROS still up: finalise the bag."""
        log.info(f"stopping ({reason})")
        self.close()

    def close(self) -> None:
        """Finalise the bag (idempotent) and log what it holds (via ``logging``: rosout may be gone)."""
        if not self.writer.closed:
            self.writer.close()
            counts = ", ".join(f"{k}: {v}" for k, v in self.writer.counts.items())
            log.info(
                f"bag closed: {self.writer.message_count} messages in {self.writer.path} ({counts})"
            )


def main(args: list[str] | None = None) -> int:
    """Console script ``recorder_node``: spin until SIGINT/SIGTERM, then finalise the bag."""
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s")
    return run_node(RecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
