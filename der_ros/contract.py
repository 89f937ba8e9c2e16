"""The ROS 2 graph contract in one place: topics, QoS, status names, prefixes and message parsers.

Every module that touches the graph -- the bridge, agent and recorder nodes, the ``der graph``
monitor, the bag writer, reader tools, export and player -- takes topic names, QoS and the
meaning of message fields from here and nowhere else. This module is ROS-free: the parsers
read attributes only, so they accept rclpy messages (live) and rosbags messages (decoded from
a bag) alike, and offline tools rebuild exactly what the nodes saw. The rclpy side (QoS
profiles, message classes) is :mod:`der_ros.contract_ros`; message *builders* live with the
nodes (:mod:`der_ros.nodes.msg_conversions`).

Why one home: when the table, the QoS and the parsers were spread over six files they drifted
(the offline export stored the commanded action while the agent stored the applied one; two QoS
tables disagreed on ``agent/metrics``). ``test/test_architecture.py`` checks that no other
module spells these strings.

Step protocol (key = sim time t_k in ns, the ``state`` header stamp): the bridge publishes
``reward`` then ``state`` stamped t_k; the agent answers with ``lane_change_cmd`` stamped t_k;
the next ``reward`` (t_{k+1}) names in ``header.frame_id`` the action the bridge applied
(``applied_action=<a>``: the agent's command, or 0 after a timeout). A transition is
(s_k, applied a_k, r_{k+1}, s_{k+1}, terminated_{k+1}, truncated_{k+1}).
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import yaml

__all__ = [
    # topic names
    "CLOCK", "STATE", "REWARD", "ODOM", "EPISODE", "COMMAND", "METRICS", "BRIDGE_DIAGNOSTICS",
    "AGENT_COMMAND", "SAFETY_EVENTS", "SAFETY_DIAGNOSTICS", "SAFETY_STATUS", "SAFETY_VERDICTS", "parse_safety_record",
    "SCENE_VEHICLES", "SCENE_ROAD", "SCENE_TOPICS",
    # status names, events, prefixes
    "EPISODE_STATUS", "METRICS_STATUS", "BRIDGE_STATUS", "EPISODE_START", "EPISODE_SUCCESS", "EPISODE_COLLISION",
    "EPISODE_TIME_LIMIT", "EPISODE_ENDS", "EPISODE_EVENTS",
    "APPLIED_ACTION_PREFIX", "POINTFIELD_FLOAT64", "FLOAT32_MAX", "ACTION_NAMES",
    # QoS and the topic table
    "QosSpec", "TopicSpec", "TOPICS", "RELIABLE_VOLATILE", "SENSOR_DATA", "topic_spec", "topic_by_name",
    "default_record_topics", "topics_markdown", "parse_qos_profiles", "merged_qos", "qos_text",
    # parsers
    "Reward", "stamp_to_ns", "header_ns", "parse_reward", "reward_from_fields", "applied_action_frame", "parse_applied_action",
    "parse_command", "cdr_command_sender", "command_action", "cloud_to_points", "points_from_buffer", "point_field_names", "odometry_pose",
    "parse_key_values", "format_value", "episode_values", "parse_episode_events", "diagnostics_to_metrics",
    # the scene markers (visualization_msgs/MarkerArray)
    "MARKER_CUBE", "MARKER_LINE_STRIP", "MARKER_ADD", "MARKER_DELETE", "MARKER_DELETEALL", "VEHICLE_NS", "LANE_NS",
    "VEHICLE_HEIGHT", "SCENE_ROLES", "EGO_ROLE", "TRAFFIC_ROLE", "ROLE_COLOURS", "LANE_COLOUR", "VehicleMarker", "LaneLine",
    "SceneUpdate", "yaw_quaternion", "role_of_colour", "parse_vehicle_markers", "parse_road_markers",
]

log = logging.getLogger(__name__)

# -- topic names (relative: resolved in the node's namespace; /clock is global) -------------------
CLOCK = "/clock"
STATE = "state"
REWARD = "reward"
ODOM = "ego/odom"
EPISODE = "episode"
COMMAND = "lane_change_cmd"
METRICS = "agent/metrics"
BRIDGE_DIAGNOSTICS = "bridge/diagnostics"
SCENE_VEHICLES = "scene/vehicles"
SCENE_ROAD = "scene/road"
#: the agent's command when a safety node sits between agent and bridge (``der graph --safety``)
AGENT_COMMAND = "agent/lane_change_cmd"
#: the safety node's per-command record (one DiagnosticArray per command) and its counters
SAFETY_EVENTS = "safety/interventions"
SAFETY_DIAGNOSTICS = "safety/diagnostics"
#: the topics a viewer (RViz, Foxglove, ``der replay render``) draws the scene from
SCENE_TOPICS = (SCENE_VEHICLES, SCENE_ROAD)

# -- DiagnosticStatus names and episode events -----------------------------------------------------
#: status name of every event on the ``episode`` topic
EPISODE_STATUS = "episode"
#: status name of the metrics on ``agent/metrics``
METRICS_STATUS = "agent/metrics"
#: status name of the bridge's counters on ``bridge/diagnostics``
BRIDGE_STATUS = "bridge"
#: status name of the safety node's records and counters
SAFETY_STATUS = "safety"
#: status messages of a safety record: the command went through, or why it became keep lane
SAFETY_VERDICTS: tuple[str, ...] = ("pass", "unsafe", "no_state", "stale", "malformed")
#: status message of an episode's first event
EPISODE_START = "start"
#: status messages of an episode's end event (the env's ``info["event"]`` values)
EPISODE_SUCCESS, EPISODE_COLLISION, EPISODE_TIME_LIMIT = "success", "collision", "time_limit"
EPISODE_ENDS = (EPISODE_SUCCESS, EPISODE_COLLISION, EPISODE_TIME_LIMIT)
EPISODE_EVENTS = (EPISODE_START, *EPISODE_ENDS)

#: names of the actions ``lane_change_cmd`` carries, by index (the env's ``ACTION_MEANINGS``)
ACTION_NAMES: tuple[str, ...] = ("keep", "left", "right")

#: ``reward.header.frame_id`` = this prefix + the action the bridge applied to reach the state
APPLIED_ACTION_PREFIX = "applied_action="
#: ``sensor_msgs/PointField.FLOAT64``: the only datatype of the ``state`` cloud's fields
POINTFIELD_FLOAT64 = 8
#: observations and rewards are stored as float32: larger values (and NaN/inf) are malformed input
FLOAT32_MAX = float(np.finfo(np.float32).max)
_NS = 1_000_000_000

# -- QoS -----------------------------------------------------------------------------------------
#: rosbag2 writes "infinite" durations (deadline, lifespan, lease) as this pair.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}
_RELIABILITY = ("reliable", "best_effort", "system_default", "best_available", "unknown")
_DURABILITY = ("volatile", "transient_local", "system_default", "best_available", "unknown")
_HISTORY = ("keep_last", "keep_all", "system_default", "unknown")
#: integer enums of rosbag2 metadata before version 9
_QOS_ENUMS = {
    "history": {0: "system_default", 1: "keep_last", 2: "keep_all"},
    "reliability": {0: "system_default", 1: "reliable", 2: "best_effort", 4: "best_available"},
    "durability": {0: "system_default", 1: "transient_local", 2: "volatile", 4: "best_available"},
}


@dataclass(frozen=True)
class QosSpec:
    """The parts of a QoS profile the graph uses; deadline/lifespan/liveliness stay default.

    Spelled as rosbag2 spells them (``reliable``, ``keep_last``...). ``to_rosbag2()`` gives the
    dict rosbag2 (metadata version 9) stores in ``offered_qos_profiles`` so ``ros2 bag play``
    can re-offer the same QoS; :func:`der_ros.contract_ros.qos_profile` gives the rclpy profile.
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

    @classmethod
    def make(cls, *, best_effort: bool = False, transient_local: bool = False, depth: int = 10) -> QosSpec:
        """KEEP_LAST ``depth`` with the two choices a subscriber has to match its publishers on."""
        return cls(reliability="best_effort" if best_effort else "reliable",
                   durability="transient_local" if transient_local else "volatile", depth=depth)

    @property
    def best_effort(self) -> bool:
        return self.reliability == "best_effort"

    @property
    def keep_all(self) -> bool:
        return self.history == "keep_all"

    @property
    def transient_local(self) -> bool:
        return self.durability == "transient_local"

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


def parse_qos_profiles(text: str | None) -> tuple[dict[str, Any], ...]:
    """rosbag2's ``offered_qos_profiles`` (a YAML list of dicts) -> tuple of dicts; () if absent.

    Both spellings are accepted: names (metadata version >= 9) and the integer enums of older
    rosbag2 versions, normalised to names (``reliable``, ``keep_last``, ...). Unreadable text
    gives () (the caller falls back to the table's QoS).
    """
    if not text:
        return ()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        log.warning("unreadable offered_qos_profiles %r; using the default QoS", text[:80])
        return ()
    if not isinstance(data, list):
        return ()
    out = []
    for prof in data:
        if not isinstance(prof, dict):
            continue
        prof = dict(prof)
        for key, table in _QOS_ENUMS.items():
            value = prof.get(key)
            if isinstance(value, int):
                prof[key] = table.get(value, "system_default")
            elif isinstance(value, str):
                prof[key] = value.lower()
        out.append(prof)
    return tuple(out)


def merged_qos(profiles: Sequence[dict[str, Any]], default_depth: int = 10) -> QosSpec:
    """One QoS to offer for a topic recorded with these publisher profiles (rosbag2 dicts).

    Reliable only if every recorded publisher was (a reliable writer would not match a
    best-effort reader's expectations otherwise), transient-local only if every one was, the
    largest KEEP_LAST depth. Graph introspection does not tell a publisher's history, so
    recorders write ``history: unknown, depth: 0``; the depth then falls back to
    ``default_depth`` (the topic table's).
    """
    if not profiles:
        return QosSpec(depth=default_depth)
    specs = [QosSpec.from_rosbag2(p) for p in profiles]
    depth = max(s.depth for s in specs) or default_depth
    return QosSpec.make(best_effort=not all(s.reliability == "reliable" for s in specs),
                        transient_local=all(s.transient_local for s in specs), depth=depth)


def qos_text(profiles: Sequence[dict[str, Any]]) -> str:
    """Offered QoS of a recorded topic for tables (``der replay info``), e.g. ``RELIABLE, KEEP_LAST 50``."""
    if not profiles:
        return "-"
    p = profiles[0]
    parts = [str(p.get("reliability", "?")).upper()]
    hist = str(p.get("history", "unknown")).lower()
    if hist == "keep_last" and p.get("depth"):
        parts.append(f"KEEP_LAST {p['depth']}")
    elif hist == "keep_all":
        parts.append("KEEP_ALL")
    durability = str(p.get("durability", "volatile")).lower()
    if durability != "volatile" or len(parts) == 1:
        parts.append(durability.upper())
    if len(profiles) > 1:
        parts.append(f"({len(profiles)} publishers)")
    return ", ".join(parts)


# -- the topic table -----------------------------------------------------------------------------
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
    #: recorded by default (``recorder_node`` ``topics``)
    record: bool = True
    fields: dict[str, str] = field(default_factory=dict)

    @property
    def short_type(self) -> str:
        """``sensor_msgs/PointCloud2`` (the ``msg`` part dropped) for tables."""
        pkg, _, name = self.msgtype.split("/")
        return f"{pkg}/{name}"


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(
        name=CLOCK,
        msgtype="rosgraph_msgs/msg/Clock",
        qos=QosSpec(reliability="best_effort", depth=1),
        publisher="bridge_node",
        subscribers=("all (use_sim_time)",),
        rate="1 per decision step",
        meaning="global simulation time, monotonic across episodes",
        units="s (sec + nanosec)",
    ),
    TopicSpec(
        name=STATE,
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
        name=REWARD,
        msgtype="geometry_msgs/msg/Vector3Stamped",
        qos=QosSpec(depth=50),
        publisher="bridge_node",
        subscribers=("agent_node", "recorder_node"),
        rate="1 per decision step, before state",
        meaning="x = reward on arriving in state k (0 at an episode start), y = terminated, z = truncated; "
        f"stamp t_k; header.frame_id = '{APPLIED_ACTION_PREFIX}<a>', the action the bridge applied in the step "
        "that led here (the agent's, or 0 after a timeout; empty at an episode's first state)",
        units="reward (unitless), flags 0/1",
    ),
    TopicSpec(
        name=ODOM,
        msgtype="nav_msgs/msg/Odometry",
        qos=SENSOR_DATA,
        publisher="bridge_node",
        subscribers=("viewers",),
        rate="1 per decision step",
        meaning="ego pose in the map frame and its speed",
        units="m, rad (quaternion), m/s",
    ),
    TopicSpec(
        name=EPISODE,
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=100),
        publisher="bridge_node",
        subscribers=("agent_node", "recorder_node"),
        rate="2 per episode (start + end event)",
        meaning=f"one status named '{EPISODE_STATUS}' per event; message {'/'.join(EPISODE_EVENTS)}; "
        "values episode, steps, return, lane_changes, mean_speed",
        units="steps, reward, count, m/s",
    ),
    TopicSpec(
        name=COMMAND,
        msgtype="sensor_msgs/msg/Joy",
        qos=QosSpec(depth=10),
        publisher="agent_node",
        subscribers=("bridge_node",),
        rate="1 per decision step",
        meaning="buttons[0] = action (0 keep, 1 left, 2 right); header.stamp = stamp of the state it answers; "
        "header.frame_id = sender id (the bridge locks onto the first sender)",
        units="action index",
    ),
    TopicSpec(
        name=METRICS,
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=50),
        publisher="agent_node",
        subscribers=("recorder_node", "der graph monitor"),
        rate="every few hundred steps and at episode ends",
        meaning=f"one status named '{METRICS_STATUS}': training metrics with stable names "
        "(charts/episodic_return, losses/td_loss, replay/h2_fraction, ...)",
        units="per metric",
    ),
    TopicSpec(
        name=BRIDGE_DIAGNOSTICS,
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=10),
        publisher="bridge_node",
        subscribers=("viewers", "tests", "bench"),
        rate="every diagnostics_every steps and at exit",
        meaning=f"one status named '{BRIDGE_STATUS}': sim_steps, steps_per_s, commands/* (accepted and every "
        "rejection), events/*, roundtrip_p50_ms / roundtrip_p99_ms; WARN once a command was rejected",
        units="counts, steps/s, ms",
        record=False,
    ),
    TopicSpec(
        name=AGENT_COMMAND,
        msgtype="sensor_msgs/msg/Joy",
        qos=QosSpec(depth=10),
        publisher="agent_node (remapped from lane_change_cmd when der graph --safety is on)",
        subscribers=("safety_node",),
        rate="1 per decision step",
        meaning="the agent's proposal, same layout as lane_change_cmd; the safety node forwards it or keep lane",
        units="action index",
        record=False,
    ),
    TopicSpec(
        name=SAFETY_EVENTS,
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=50),
        publisher="safety_node",
        subscribers=("recorder_node", "der replay plot / render"),
        rate="1 per decision step",
        meaning=f"one status named '{SAFETY_STATUS}' per command; message = verdict ({'/'.join(SAFETY_VERDICTS)}); "
        "values proposed, applied, interventions (running count); stamp t_k of the answered state",
        units="action index, count",
    ),
    TopicSpec(
        name=SAFETY_DIAGNOSTICS,
        msgtype="diagnostic_msgs/msg/DiagnosticArray",
        qos=QosSpec(depth=10),
        publisher="safety_node",
        subscribers=("der graph", "viewers"),
        rate="every diagnostics_every commands and at exit",
        meaning=f"one status named '{SAFETY_STATUS}': commands, interventions and one counter per verdict",
        units="counts",
        record=False,
    ),
    TopicSpec(
        name=SCENE_VEHICLES,
        msgtype="visualization_msgs/msg/MarkerArray",
        qos=QosSpec(depth=10),
        publisher="bridge_node (markers:=true)",
        subscribers=("recorder_node", "RViz / Foxglove", "der replay render"),
        rate="1 per decision step, after state",
        meaning="every vehicle as a CUBE in the map frame (ns 'vehicles', id stable while the vehicle exists, "
        "text = SUMO id, pose = its centre, colour = its role: ego or one of the neighbour slots or traffic); "
        "a DELETE for each vehicle that left; stamp t_k",
        units="m, rad (quaternion)",
    ),
    TopicSpec(
        name=SCENE_ROAD,
        msgtype="visualization_msgs/msg/MarkerArray",
        qos=QosSpec(durability="transient_local", depth=1),
        publisher="bridge_node (markers:=true)",
        subscribers=("recorder_node", "RViz / Foxglove", "der replay render"),
        rate="once at start (latched: late subscribers get it)",
        meaning="every lane of the SUMO network as a LINE_STRIP along its centre line (ns 'lanes', "
        "scale.x = lane width, text = SUMO lane id), map frame",
        units="m",
    ),
)
_BY_NAME = {spec.name: spec for spec in TOPICS}


def topic_spec(name: str) -> TopicSpec:
    """The table entry of a contract topic name (``STATE``, ``CLOCK``...); KeyError if not one."""
    return _BY_NAME[name]


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
    """The topics the recorder subscribes to unless told otherwise."""
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


# -- parsers (rclpy and rosbags messages alike) ---------------------------------------------------
class Reward(NamedTuple):
    """A parsed ``reward`` message."""

    stamp_ns: int
    reward: float
    terminated: bool
    truncated: bool
    #: the action the bridge applied in the step that led here; None at an episode's first state
    applied_action: int | None


def stamp_to_ns(t: Any) -> int:
    """``builtin_interfaces/Time`` -> nanoseconds (the step key of the graph)."""
    return int(t.sec) * _NS + int(t.nanosec)


def header_ns(msg: Any) -> int:
    """The header stamp of a message in nanoseconds."""
    return stamp_to_ns(msg.header.stamp)


def applied_action_frame(action: int | None) -> str:
    """The ``reward`` frame_id naming the applied action ("" for an episode's first state)."""
    return "" if action is None else f"{APPLIED_ACTION_PREFIX}{int(action)}"


def parse_applied_action(msg: Any) -> int | None:
    """The ``applied_action=<a>`` of a reward's frame_id (None when absent); ValueError if garbled."""
    return _applied_action(str(msg.header.frame_id))


def _applied_action(frame: str) -> int | None:
    if not frame.startswith(APPLIED_ACTION_PREFIX):
        return None
    try:
        return int(frame[len(APPLIED_ACTION_PREFIX):])
    except ValueError:
        raise ValueError(f"reward frame_id = {frame!r}, expected '{APPLIED_ACTION_PREFIX}<integer>'") from None


def parse_reward(msg: Any) -> Reward:
    """``reward`` message -> :class:`Reward`; ValueError naming the field if malformed."""
    v = msg.vector
    return reward_from_fields(header_ns(msg), str(msg.header.frame_id), v.x, v.y, v.z)


def reward_from_fields(stamp_ns: int, frame_id: str, x: float, y: float, z: float) -> Reward:
    """:func:`parse_reward` from the message's fields (the agent node's CDR reader decodes them itself)."""
    if not math.isfinite(x) or abs(x) > FLOAT32_MAX:
        raise ValueError(f"reward x = {x!r}, expected a finite number within float32 range (it is stored as float32)")
    for name, flag in (("y (terminated)", y), ("z (truncated)", z)):
        if flag not in (0.0, 1.0):
            raise ValueError(f"reward {name} = {flag!r}, expected 0 or 1")
    return Reward(int(stamp_ns), float(x), y == 1.0, z == 1.0, _applied_action(frame_id))


def parse_command(msg: Any) -> tuple[int, list[int], list[float], str]:
    """``lane_change_cmd`` -> (stamp_ns, buttons, axes, sender); validation is the receiver's job."""
    return header_ns(msg), [int(b) for b in msg.buttons], [float(a) for a in msg.axes], str(msg.header.frame_id)


def cdr_command_sender(data: bytes | memoryview) -> str | None:
    """The sender id (``header.frame_id``) of a *serialized* ``lane_change_cmd``, read from its CDR
    bytes without decoding the rest; None if the bytes cannot hold a header.

    Why a parser of our own for four fields: a receiver that must screen a flood of commands by
    sender (the bridge, after its first-publisher lock) pays ~50 us per message to have rclpy
    build a ``sensor_msgs/Joy`` and judge it, and ~4-11 us to read the sender here and drop it
    (measured on 800 queued commands, 2-core machine), so a flood from a stray publisher cannot
    outpace it. Layout (XCDR1, ``std_msgs/Header`` first): 4-byte encapsulation (byte 1: 1 =
    little endian), int32 sec, uint32 nanosec, uint32 length of frame_id including its NUL, the
    characters.
    """
    if len(data) < 16:
        return None
    order = "<" if data[1] == 1 else ">"
    (length,) = struct.unpack_from(f"{order}I", data, 12)
    if length < 1 or 16 + length > len(data):
        return None
    return bytes(data[16:16 + length - 1]).decode("utf-8", errors="replace")


def command_action(msg: Any) -> int:
    """The action of a ``lane_change_cmd`` (``buttons[0]``); ValueError without one."""
    if len(msg.buttons) < 1:
        raise ValueError("lane_change_cmd without buttons[0] (the action)")
    return int(msg.buttons[0])


def point_field_names(msg: Any) -> tuple[str, ...]:
    """Names of the fields of a PointCloud2, in order."""
    return tuple(str(f.name) for f in msg.fields)


def cloud_to_points(msg: Any, fields: Sequence[str] | None = None) -> np.ndarray:
    """``state`` PointCloud2 -> ``(width * height, n_fields)`` float64 array, bit-exact.

    Every field must be FLOAT64, count 1, packed in order (the bridge's layout); ``fields``
    (e.g. ``observation.POINT_FIELDS``) also pins the names; every value must be finite and
    within float32's range (the simulator never sends others; a NaN would poison the replay).
    Anything else raises ValueError naming the field: a silently re-typed observation would break
    the promise that the agent, the environment and the export see bit-identical observations.
    """
    names = point_field_names(msg)
    if fields is not None and names != tuple(fields):
        raise ValueError(f"state fields = {names}, expected {tuple(fields)}")
    for i, f in enumerate(msg.fields):
        if f.datatype != POINTFIELD_FLOAT64 or f.offset != 8 * i or f.count != 1:
            raise ValueError(
                f"state field {f.name!r}: datatype {f.datatype} offset {f.offset} count {f.count}, "
                f"expected FLOAT64 ({POINTFIELD_FLOAT64}) at offset {8 * i}, count 1"
            )
    step = 8 * len(names)
    n = int(msg.width) * int(msg.height)
    data = msg.data
    if int(msg.point_step) != step or len(data) != n * step:
        raise ValueError(
            f"state point_step = {msg.point_step}, {len(data)} data bytes for {n} points, "
            f"expected point_step {step} and {n * step} bytes"
        )
    return points_from_buffer(data, n, names, bool(msg.is_bigendian))


def points_from_buffer(data: Any, n: int, names: Sequence[str], bigendian: bool = False) -> np.ndarray:
    """The ``(n, len(names))`` float64 points of a ``state``'s data bytes (FLOAT64 fields in order), a
    copy; ValueError naming the point and field of a value that is not finite or beyond float32's range.
    The last step of :func:`cloud_to_points`, shared with the CDR reader of the agent node
    (:mod:`der_ros.bag.step_cdr_read`), which has checked the rest of the layout itself."""
    dtype = np.dtype(">f8" if bigendian else "<f8")
    # rclpy gives array.array/bytes, rosbags a uint8 ndarray: all expose the buffer protocol
    points = np.frombuffer(data, dtype=dtype).astype(np.float64).reshape(n, len(names))
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(points) | (np.abs(points) > FLOAT32_MAX)
    if bad.any():  # a NaN/inf point would reach the observation (and the replay) of every consumer
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"state point {row} field {names[col]!r} = {points[row, col]!r}, expected a finite number "
                         "within float32 range")
    return points


def odometry_pose(msg: Any) -> tuple[int, float, float, float, float]:
    """``ego/odom`` -> (stamp_ns, x, y, SUMO angle in degrees [0, 360), forward speed).

    SUMO angles are degrees clockwise from north; ROS (REP 103) yaw is counter-clockwise from
    the x axis (east), so ``angle = 90 - degrees(yaw)``.
    """
    q = msg.pose.pose.orientation
    yaw = 2.0 * math.atan2(q.z, q.w)
    angle = (90.0 - math.degrees(yaw)) % 360.0
    p = msg.pose.pose.position
    return header_ns(msg), p.x, p.y, angle, msg.twist.twist.linear.x


def format_value(value: object) -> str:
    """A ``diagnostic_msgs/KeyValue`` value: ``repr`` of floats (exact round trip), ``str`` otherwise."""
    return repr(value) if isinstance(value, float) else str(value)


def _parse_value(text: str) -> int | float | str:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def episode_values(episode: int, steps: int, ret: float | None = 0.0, lane_changes: int = 0,
                   mean_speed: float = 0.0, **extra: object) -> dict[str, object]:
    """The key/values of an ``episode`` event, in the order the bridge writes them (start events
    carry only ``episode`` and ``steps``: pass ``ret=None``)."""
    out: dict[str, object] = {"episode": int(episode), "steps": int(steps)}
    if ret is not None:
        out.update({"return": float(ret), "lane_changes": int(lane_changes), "mean_speed": float(mean_speed)})
    out.update(extra)
    return out


def parse_safety_record(msg: Any) -> tuple[int, str, int, int, int] | None:
    """A ``safety/interventions`` DiagnosticArray -> (stamp_ns, verdict, proposed, applied, interventions),
    None when it holds no safety status."""
    for status in msg.status:
        if status.name == SAFETY_STATUS:
            values = parse_key_values(status.values)
            return (header_ns(msg), str(status.message), int(float(values.get("proposed", -1))),
                    int(float(values.get("applied", 0))), int(float(values.get("interventions", 0))))  # fmt: skip
    return None


def parse_key_values(values: Iterable[Any]) -> dict[str, int | float | str]:
    """``diagnostic_msgs/KeyValue`` items -> key -> int, float or text (inverse of :func:`format_value`)."""
    return {str(kv.key): _parse_value(str(kv.value)) for kv in values}


def parse_episode_events(msg: Any) -> list[tuple[int, str, dict[str, int | float | str]]]:
    """Every ``episode`` status of a DiagnosticArray as (stamp_ns, event, values)."""
    stamp = header_ns(msg)
    return [
        (stamp, str(s.message), parse_key_values(s.values))
        for s in msg.status
        if s.name == EPISODE_STATUS
    ]


def diagnostics_to_metrics(msg: Any, names: Sequence[str] | None = None) -> dict[str, float]:
    """Every numeric key/value of the statuses (optionally only those named ``names``) as floats."""
    out: dict[str, float] = {}
    for s in msg.status:
        if names is not None and s.name not in names:
            continue
        for kv in s.values:
            try:
                out[str(kv.key)] = float(kv.value)
            except ValueError:
                continue
    return out



# -- the scene markers (``scene/vehicles``, ``scene/road``) ---------------------------------------
# visualization_msgs/Marker constants (the message's own values; spelled here so ROS-free code
# can build and read markers).
MARKER_CUBE, MARKER_LINE_STRIP = 1, 4
MARKER_ADD, MARKER_DELETE, MARKER_DELETEALL = 0, 2, 3
#: marker namespace of the vehicles on ``scene/vehicles`` and of the lanes on ``scene/road``
VEHICLE_NS, LANE_NS = "vehicles", "lanes"
#: height (z size) of a vehicle's cube, m; its centre sits at half this height
VEHICLE_HEIGHT = 1.5
#: the learning vehicle
EGO_ROLE = "ego"
#: a vehicle that is neither the ego nor in a neighbour slot
TRAFFIC_ROLE = "traffic"
#: the role of a vehicle in the scene: the ego, one of the observation's neighbour slots
#: (``sumo_bridge.observation.SLOT_NAMES``, in order), or other traffic
SCENE_ROLES: tuple[str, ...] = (EGO_ROLE, "leader", "follower", "left_leader", "left_follower", "right_leader",
                                "right_follower", TRAFFIC_ROLE)  # fmt: skip
#: RGBA of each role: the ego red, the slots of the current lane orange/yellow, of the left lane
#: greens, of the right lane blues (leaders darker than followers), traffic grey. A viewer tells
#: the roles apart by colour alone, and :func:`role_of_colour` reads a role back from a marker.
ROLE_COLOURS: dict[str, tuple[float, float, float, float]] = {
    EGO_ROLE: (0.85, 0.10, 0.10, 1.0),
    "leader": (1.0, 0.55, 0.0, 1.0),
    "follower": (0.95, 0.80, 0.15, 1.0),
    "left_leader": (0.05, 0.55, 0.20, 1.0),
    "left_follower": (0.45, 0.80, 0.40, 1.0),
    "right_leader": (0.10, 0.35, 0.85, 1.0),
    "right_follower": (0.45, 0.70, 1.0, 1.0),
    TRAFFIC_ROLE: (0.62, 0.62, 0.62, 1.0),
}
#: RGBA of the lanes on ``scene/road``
LANE_COLOUR = (0.30, 0.30, 0.33, 1.0)
_COLOUR_TOLERANCE = 2e-3  # ColorRGBA is float32


class VehicleMarker(NamedTuple):
    """One vehicle of ``scene/vehicles``: the cube's centre and heading in the map frame."""

    marker_id: int
    vehicle_id: str
    role: str
    x: float
    y: float
    #: heading, radians counter-clockwise from the map's x axis (REP 103)
    yaw: float
    length: float
    width: float


class LaneLine(NamedTuple):
    """One lane of ``scene/road``: its centre line (``(n, 2)`` float64, m) and width (m)."""

    lane_id: str
    points: np.ndarray
    width: float


class SceneUpdate(NamedTuple):
    """What one ``scene/vehicles`` message changes: vehicles added or moved, marker ids deleted, and
    whether everything known before was cleared first (a DELETEALL clears what came before it,
    markers being applied in array order as RViz applies them)."""

    stamp_ns: int
    vehicles: list[VehicleMarker]
    deleted: list[int]
    delete_all: bool


def yaw_quaternion(yaw: float) -> tuple[float, float]:
    """(z, w) of the quaternion of a rotation by ``yaw`` about the z axis (x = y = 0)."""
    return math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def role_of_colour(r: float, g: float, b: float) -> str:
    """The role whose colour (:data:`ROLE_COLOURS`) this is; ValueError naming the colour if none is."""
    for role, (cr, cg, cb, _a) in ROLE_COLOURS.items():
        if abs(r - cr) <= _COLOUR_TOLERANCE and abs(g - cg) <= _COLOUR_TOLERANCE and abs(b - cb) <= _COLOUR_TOLERANCE:
            return role
    raise ValueError(f"vehicle marker colour = ({r:.3f}, {g:.3f}, {b:.3f}), not the colour of any role in {SCENE_ROLES}")


def parse_vehicle_markers(msg: Any) -> SceneUpdate:
    """A ``scene/vehicles`` MarkerArray -> :class:`SceneUpdate` (markers of other namespaces are
    ignored, so a viewer may add its own); ValueError naming the marker and field if malformed."""
    vehicles: list[VehicleMarker] = []
    deleted: list[int] = []
    delete_all = False
    stamp = 0
    for i, m in enumerate(msg.markers):
        if i == 0:
            stamp = header_ns(m)
        if m.action == MARKER_DELETEALL:
            delete_all, vehicles, deleted = True, [], []
            continue
        if m.ns != VEHICLE_NS:
            continue
        if m.action == MARKER_DELETE:
            deleted.append(int(m.id))
            continue
        if m.action != MARKER_ADD:
            raise ValueError(f"scene/vehicles marker {i} (id {m.id}): action = {m.action}, expected "
                             f"ADD ({MARKER_ADD}), DELETE ({MARKER_DELETE}) or DELETEALL ({MARKER_DELETEALL})")
        if m.type != MARKER_CUBE:
            raise ValueError(f"scene/vehicles marker {i} (id {m.id}): type = {m.type}, expected CUBE ({MARKER_CUBE})")
        q = m.pose.orientation
        c = m.color
        vehicles.append(VehicleMarker(
            int(m.id), str(m.text), role_of_colour(c.r, c.g, c.b), float(m.pose.position.x), float(m.pose.position.y),
            2.0 * math.atan2(q.z, q.w), float(m.scale.x), float(m.scale.y),
        ))  # fmt: skip
    return SceneUpdate(stamp, vehicles, deleted, delete_all)


def parse_road_markers(msg: Any) -> list[LaneLine]:
    """The lanes of a ``scene/road`` MarkerArray (LINE_STRIPs of namespace ``lanes``), in message order."""
    lanes = []
    for i, m in enumerate(msg.markers):
        if m.ns != LANE_NS or m.action != MARKER_ADD:
            continue
        if m.type != MARKER_LINE_STRIP or len(m.points) < 2:
            raise ValueError(f"scene/road marker {i} ({m.text!r}): type {m.type} with {len(m.points)} points, "
                             f"expected a LINE_STRIP ({MARKER_LINE_STRIP}) of at least 2 points")
        pts = np.array([(p.x, p.y) for p in m.points], dtype=np.float64)
        lanes.append(LaneLine(str(m.text), pts, float(m.scale.x)))
    return lanes
