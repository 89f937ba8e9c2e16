"""The der_ros ROS 2 graph's topics as data (ROS-free).

One table, used by

* the recorder node (default topic list and the QoS it subscribes with),
* the bag writer (offered QoS written into the bag when a publisher's QoS is unknown),
* the offline bag tools (which topic holds what, in which units),
* the README (:func:`topics_markdown` renders the table).

The table mirrors "ROS 2 graph contract" in ``docs/architecture.md``; names are relative
(resolved under the node's namespace) except ``/clock``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "QosSpec",
    "TopicSpec",
    "TOPICS",
    "RELIABLE_VOLATILE",
    "SENSOR_DATA",
    "topic_by_name",
    "default_record_topics",
    "topics_markdown",
    "parse_key_values",
]

#: rosbag2 writes "infinite" durations (deadline, lifespan, lease) as this pair.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}
_RELIABILITY = ("reliable", "best_effort", "system_default", "best_available", "unknown")
_DURABILITY = ("volatile", "transient_local", "system_default", "best_available", "unknown")
_HISTORY = ("keep_last", "keep_all", "system_default", "unknown")


@dataclass(frozen=True)
class QosSpec:
    """The parts of a QoS profile the graph uses; deadline/lifespan/liveliness stay default.

    ``to_rosbag2()`` gives the dict rosbag2 (metadata version 9) stores in
    ``offered_qos_profiles`` so ``ros2 bag play`` can re-offer the same QoS.
    """

    reliability: str = "reliable"
    durability: str = "volatile"
    history: str = "keep_last"
    depth: int = 10

    def __post_init__(self) -> None:
        if self.reliability not in _RELIABILITY:
            raise ValueError(f"QosSpec.reliability = {self.reliability!r}, expected one of {_RELIABILITY}")
        if self.durability not in _DURABILITY:
            raise ValueError(f"QosSpec.durability = {self.durability!r}, expected one of {_DURABILITY}")
        if self.history not in _HISTORY:
            raise ValueError(f"QosSpec.history = {self.history!r}, expected one of {_HISTORY}")
        if not isinstance(self.depth, int) or self.depth < 0:
            raise ValueError(f"QosSpec.depth = {self.depth!r}, expected an integer >= 0")

    def to_rosbag2(self) -> dict[str, Any]:
        """One entry of rosbag2's ``offered_qos_profiles`` list (version 9 spelling)."""
        return {
            "history": self.history,
            "depth": int(self.depth),
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": dict(_INFINITE),
            "lifespan": dict(_INFINITE),
            "liveliness": "automatic",
            "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False,
        }

    @classmethod
    def from_rosbag2(cls, d: dict[str, Any]) -> QosSpec:
        """Inverse of :meth:`to_rosbag2` (unknown spellings become ``unknown``, as rosbag2 writes)."""

        def pick(value: Any, allowed: tuple[str, ...]) -> str:
            text = str(value).lower()
            return text if text in allowed else "unknown"

        return cls(
            reliability=pick(d.get("reliability", "reliable"), _RELIABILITY),
            durability=pick(d.get("durability", "volatile"), _DURABILITY),
            history=pick(d.get("history", "keep_last"), _HISTORY),
            depth=int(d.get("depth", 0) or 0),
        )

    def short(self) -> str:
        """Compact text for tables, e.g. ``RELIABLE, KEEP_LAST 50``."""
        hist = "KEEP_ALL" if self.history == "keep_all" else f"{self.history.upper()} {self.depth}"
        parts = [self.reliability.upper(), hist]
        if self.durability != "volatile":
            parts.append(self.durability.upper())
        return ", ".join(parts)


#: ``rclpy.qos.QoSProfile(depth=10)``.
RELIABLE_VOLATILE = QosSpec()
#: ``rclpy.qos.qos_profile_sensor_data``.
SENSOR_DATA = QosSpec(reliability="best_effort", depth=5)


@dataclass(frozen=True)
class TopicSpec:
    """One topic of the graph: what it carries, who publishes it, at what rate, in which units."""

    name: str
    msgtype: str
    qos: QosSpec
    publisher: str
    subscribers: tuple[str, ...]
    rate: str
    meaning: str
    units: str
    record: bool = True
    fields: dict[str, str] = field(default_factory=dict)

    @property
    def short_type(self) -> str:
        """``sensor_msgs/PointCloud2`` (the ``msg`` part dropped) for tables."""
        pkg, _, name = self.msgtype.split("/")
        return f"{pkg}/{name}"


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(
        name="/clock",
        msgtype="rosgraph_msgs/msg/Clock",
        qos=QosSpec(reliability="best_effort", depth=1),
        publisher="bridge_node",
        subscribers=("all (use_sim_time)",),
        rate="1 per decision step",
        meaning="global simulation time, monotonic across episodes",
        units="s (sec + nanosec)",
    ),
    TopicSpec(
        name="state",
        msgtype="sensor_msgs/msg/PointCloud2",
        qos=QosSpec(depth=50),
        publisher="bridge_node",
        subscribers=("agent_node", "recorder_node"),
        rate="1 per decision step",
        meaning="row 0 ego vehicle, then the neighbour slots (FLOAT64 fields = observation.POINT_FIELDS); "
        "header.stamp = sim time t_k, the step key",
        units="m (x, y, z, gap), m/s (speed, rel_speed), lane index",
    ),
    TopicSpec(
        name="reward",
        msgtype="geometry_msgs/msg/Vector3Stamped",
        qos=QosSpec(depth=50),
        publisher="bridge_node",
        subscribers=("agent_node",),
        rate="1 per decision step, before state",
        meaning="x = reward on arriving in state k (0 at an episode start), y = terminated, z = truncated; "
        "stamp t_k",
        units="reward (unitless), flags 0/1",
    ),
    TopicSpec(
        name="ego/odom",
        msgtype="nav_msgs/msg/Odometry",
        qos=SENSOR_DATA,
        publisher="bridge_node",
        subscribers=("viewers",),
        rate="1 per decision step",
        meaning="ego pose in the map frame and its speed",
        units="m, rad (quaternion), m/s",
    ),
    TopicSpec(
        name="episode",
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=100),
        publisher="bridge_node",
        subscribers=("agent_node", "recorder_node"),
        rate="2 per episode (start + end event)",
        meaning="one status named 'episode' per event; message start/success/collision/time_limit; "
        "values episode, steps, return, lane_changes, mean_speed",
        units="steps, reward, count, m/s",
    ),
    TopicSpec(
        name="lane_change_cmd",
        msgtype="sensor_msgs/msg/Joy",
        qos=QosSpec(depth=10),
        publisher="agent_node",
        subscribers=("bridge_node",),
        rate="1 per decision step",
        meaning="buttons[0] = action (0 keep, 1 left, 2 right); header.stamp = stamp of the state it answers",
        units="action index",
    ),
    TopicSpec(
        name="agent/metrics",
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=10),
        publisher="agent_node",
        subscribers=("recorder_node", "der graph monitor"),
        rate="every few hundred steps and at episode ends",
        meaning="training metrics with stable names (charts/episodic_return, losses/td_loss, replay/h2_fraction, ...)",
        units="per metric",
    ),
)


def topic_by_name(name: str) -> TopicSpec | None:
    """The spec of ``name`` (relative or absolute, e.g. ``/ns/state`` matches ``state``)."""
    bare = name.lstrip("/")
    for spec in TOPICS:
        if spec.name.lstrip("/") == bare:
            return spec
    # A namespaced absolute name: match the longest table name it ends with.
    best: TopicSpec | None = None
    for spec in TOPICS:
        if not spec.name.startswith("/") and bare.endswith("/" + spec.name):
            if best is None or len(spec.name) > len(best.name):
                best = spec
    return best


def default_record_topics() -> list[str]:
    """The topics the recorder subscribes to unless told otherwise (all of the table)."""
    return [spec.name for spec in TOPICS if spec.record]


def topics_markdown() -> str:
    """The topic table as GitHub Markdown, for the README (kept in sync by a test)."""
    lines = [
        "| topic | type | publisher -> subscribers | QoS | rate | meaning | units |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in TOPICS:
        lines.append(
            f"| `{s.name}` | {s.short_type} | {s.publisher} -> {', '.join(s.subscribers)} | {s.qos.short()} "
            f"| {s.rate} | {s.meaning.replace('|', '/')} | {s.units} |"
        )
    return "\n".join(lines) + "\n"


def parse_key_values(values: Iterable[Any]) -> dict[str, int | float | str]:
    """``diagnostic_msgs/KeyValue`` items (rclpy or decoded from a bag) -> key -> int, float or text.

    The inverse of how the ``episode`` topic's values are written (``str`` of ints, ``repr`` of floats).
    """
    return {kv.key: _parse_value(kv.value) for kv in values}


def _parse_value(text: str) -> int | float | str:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text
