"""The rclpy face of the graph contract: QoS profiles and message classes (needs ROS 2).

:mod:`der_ros.contract` holds the QoS of every topic as ROS-free :class:`~der_ros.contract.QosSpec`;
this module is the one place that turns them into ``rclpy.qos.QoSProfile`` (for the nodes, the
``der graph`` monitor and ``der bag play``) and turns a publisher's profile, seen through graph
introspection, back into the rosbag2 spelling the recorder writes into a bag. Only modules that
already need rclpy import it; the ROS-free cores never do.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from der_ros.contract import QosSpec, topic_spec

__all__ = ["qos_profile", "topic_qos", "qos_to_rosbag2", "message_class"]

_INF_NS = 2**63 - 1
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def qos_profile(spec: QosSpec) -> QoSProfile:
    """An rclpy profile for ``spec`` (KEEP_ALL when the spec says so, KEEP_LAST ``depth`` otherwise)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if spec.keep_all else HistoryPolicy.KEEP_LAST,
        depth=max(int(spec.depth), 1),
        reliability=ReliabilityPolicy.BEST_EFFORT if spec.best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if spec.transient_local else DurabilityPolicy.VOLATILE,
    )


def topic_qos(name: str, depth: int | None = None) -> QoSProfile:
    """The rclpy profile of a contract topic (``contract.STATE``, ``contract.CLOCK``...); ``depth``
    replaces the table's KEEP_LAST depth (a subscriber's own queue, e.g. the bridge's commands)."""
    spec = topic_spec(name).qos
    return qos_profile(spec if depth is None else dataclasses.replace(spec, depth=int(depth)))


def _duration_dict(d: Any) -> dict[str, int]:
    ns = int(getattr(d, "nanoseconds", 0))
    if ns >= _INF_NS or ns < 0 or str(d) == "Infinite":
        return dict(_INFINITE)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def qos_to_rosbag2(q: Any) -> dict[str, Any]:
    """An rclpy ``QoSProfile`` (e.g. a publisher's, from graph introspection) as a rosbag2 QoS dict."""
    return {
        "history": q.history.name.lower(),
        "depth": int(q.depth),
        "reliability": q.reliability.name.lower(),
        "durability": q.durability.name.lower(),
        "deadline": _duration_dict(q.deadline),
        "lifespan": _duration_dict(q.lifespan),
        "liveliness": q.liveliness.name.lower(),
        "liveliness_lease_duration": _duration_dict(q.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": bool(q.avoid_ros_namespace_conventions),
    }


def message_class(msgtype: str) -> type | None:
    """``pkg/msg/Type`` -> the generated Python class (None if the package is not installed)."""
    try:
        pkg, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        return None
