"""The ROS 2 graph's topics: names, QoS, status names and the topic table (who publishes what, with which QoS).

Every module that touches the graph -- the bridge, agent and recorder nodes, the ``der graph``
monitor, the bag writer, reader tools, export and player -- takes topic names and QoS from here
and nowhere else; what each message holds, field by field and byte by byte, is the per-message
module of the same package (:mod:`~der_ros.contract.state`, :mod:`~der_ros.contract.reward`,
:mod:`~der_ros.contract.command`, :mod:`~der_ros.contract.odometry`, :mod:`~der_ros.contract.events`,
:mod:`~der_ros.contract.scene`). ROS-free; the rclpy side (QoS profiles, message classes) is
:mod:`der_ros.contract_ros`.

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
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from der_ros.contract.reward import APPLIED_ACTION_PREFIX
from der_ros.yaml_loader import YamlError, load_yaml_text

__all__ = [
    # topic names
    "CLOCK", "STATE", "REWARD", "ODOM", "EPISODE", "COMMAND", "METRICS", "BRIDGE_DIAGNOSTICS",
    "SCENE_VEHICLES", "SCENE_ROAD", "SCENE_TOPICS", "TF", "TF_MSGTYPE", "TF_QOS",
    "AGENT_COMMAND", "SAFETY_EVENTS", "SAFETY_DIAGNOSTICS", "SAFETY_STATUS", "SAFETY_VERDICTS",
    # status names and episode events
    "EPISODE_STATUS", "METRICS_STATUS", "BRIDGE_STATUS", "EPISODE_START", "EPISODE_SUCCESS", "EPISODE_COLLISION",
    "EPISODE_TIME_LIMIT", "EPISODE_MISSED", "EPISODE_ENDS", "EPISODE_EVENTS",
    # QoS and the topic table
    "QosSpec", "TopicSpec", "TOPICS", "RELIABLE_VOLATILE", "SENSOR_DATA", "topic_spec", "topic_by_name",
    "default_record_topics", "topics_markdown", "parse_qos_profiles", "merged_qos", "qos_text",
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
#: the topics a viewer (RViz, Foxglove, ``der bag render``) draws the scene from
SCENE_TOPICS = (SCENE_VEHICLES, SCENE_ROAD)
#: ``map -> ego`` (the ego's pose, the parent frame of ``state``) for viewers that place frames from
#: tf (Foxglove's 3D panel, RViz). Written into the bags -- by the recorder from each ``ego/odom``
#: (same stamp and pose), by the greedy-episode recorder from the env -- not published live: the
#: nodes do not depend on the tf2_msgs package (rosbags knows the type without it).
TF = "/tf"
TF_MSGTYPE = "tf2_msgs/msg/TFMessage"

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
#: the exit of a scenario with a goal edge was missed (file scenarios, e.g. ``exit``: docs/scenarios.md)
EPISODE_MISSED = "missed"
EPISODE_ENDS = (EPISODE_SUCCESS, EPISODE_COLLISION, EPISODE_TIME_LIMIT, EPISODE_MISSED)
EPISODE_EVENTS = (EPISODE_START, *EPISODE_ENDS)


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
#: the QoS tf2's broadcasters offer on ``/tf`` (reliable, volatile, depth 100)
TF_QOS = QosSpec(depth=100)


def parse_qos_profiles(text: str | None) -> tuple[dict[str, Any], ...]:
    """rosbag2's ``offered_qos_profiles`` (a YAML list of dicts) -> tuple of dicts; () if absent.

    Both spellings are accepted: names (metadata version >= 9) and the integer enums of older
    rosbag2 versions, normalised to names (``reliable``, ``keep_last``, ...). Unreadable text
    gives () (the caller falls back to the table's QoS).
    """
    if not text:
        return ()
    try:
        data = load_yaml_text(text, "offered_qos_profiles")
    except YamlError:
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
    """Offered QoS of a recorded topic for tables (``der bag info``), e.g. ``RELIABLE, KEEP_LAST 50``."""
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
        "values episode, steps, return, lane_changes, mean_speed; end events also imposed_brake (the harshest "
        "deceleration of the ego's new follower after its lane changes) and, on success, time_to_success",
        units="steps, reward, count, m/s, m/s², s",
    ),
    TopicSpec(
        name=COMMAND,
        msgtype="sensor_msgs/msg/Joy",
        qos=QosSpec(depth=10),
        publisher="agent_node",
        subscribers=("bridge_node",),
        rate="1 per decision step",
        meaning="buttons[0] = action (0 keep, 1 left, 2 right; 3 faster, 4 slower in scenarios with speed actions); header.stamp = stamp of the state it answers; "
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
        subscribers=("recorder_node", "der bag plot / render"),
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
        subscribers=("recorder_node", "RViz / Foxglove", "der bag render"),
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
        subscribers=("recorder_node", "RViz / Foxglove", "der bag render"),
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
