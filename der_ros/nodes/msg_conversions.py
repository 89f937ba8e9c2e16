"""Pure conversions between core data (numpy arrays, dicts, nanoseconds) and ROS 2 messages.

The message layouts are the "ROS 2 graph contract" of docs/architecture.md. Every function is
pure (no node, no clock) so round trips are unit-testable; decoders raise :class:`ValueError`
naming the field and the value when a message does not follow the contract, so a node can
reject bad input where it enters.

Hot-path notes: the PointCloud2 field layout is computed once per field tuple (cached), the payload
is ``ndarray.tobytes()`` on the way out and ``np.frombuffer`` on the way in (no per-point
Python loop).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import lru_cache

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2, PointField
from std_msgs.msg import Header

from der_ros.bag.topics import parse_key_values
from sumo_bridge.observation import POINT_FIELDS

__all__ = [
    "EPISODE_STATUS_NAME",
    "METRICS_STATUS_NAME",
    "ns_to_time",
    "time_to_ns",
    "make_clock",
    "points_to_cloud",
    "cloud_to_points",
    "make_odometry",
    "odometry_pose",
    "make_reward",
    "parse_reward",
    "parse_applied_action",
    "APPLIED_ACTION_PREFIX",
    "make_command",
    "parse_command",
    "make_episode_event",
    "parse_episode_events",
    "metrics_to_diagnostics",
    "diagnostics_to_metrics",
]

_NS_PER_S = 1_000_000_000
#: DiagnosticStatus.name of the events on the ``episode`` topic.
EPISODE_STATUS_NAME = "episode"
#: DiagnosticStatus.name of the status carrying the metrics on ``agent/metrics``.
METRICS_STATUS_NAME = "agent/metrics"


# -- time -----------------------------------------------------------------------------------------
def ns_to_time(ns: int) -> Time:
    """Nanoseconds (>= 0) -> builtin_interfaces/Time."""
    ns = int(ns)
    if ns < 0:
        raise ValueError(f"time = {ns} ns, expected >= 0")
    sec, nanosec = divmod(ns, _NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def time_to_ns(t: Time) -> int:
    """builtin_interfaces/Time -> nanoseconds (the step key of the graph contract)."""
    return int(t.sec) * _NS_PER_S + int(t.nanosec)


def _header(stamp_ns: int, frame_id: str) -> Header:
    return Header(stamp=ns_to_time(stamp_ns), frame_id=frame_id)


def make_clock(stamp_ns: int) -> Clock:
    """rosgraph_msgs/Clock at ``stamp_ns``."""
    return Clock(clock=ns_to_time(stamp_ns))


# -- state: points <-> PointCloud2 ----------------------------------------------------------------
@lru_cache(maxsize=8)
def _field_layout(names: tuple[str, ...]) -> tuple[tuple[str, int], ...]:
    return tuple((n, 8 * i) for i, n in enumerate(names))


def _point_fields(names: tuple[str, ...]) -> list[PointField]:
    # Fresh PointField objects per message (~10 us): rosidl messages are mutable, and a cached
    # list shared between messages would let one consumer's edit corrupt every later message.
    return [PointField(name=n, offset=o, datatype=PointField.FLOAT64, count=1) for n, o in _field_layout(names)]


def points_to_cloud(
    points: np.ndarray, stamp_ns: int, frame_id: str = "ego", fields: tuple[str, ...] = POINT_FIELDS
) -> PointCloud2:
    """A ``(n, len(fields))`` float64 array -> an unordered (height 1) PointCloud2, little endian."""
    pts = np.ascontiguousarray(points, dtype="<f8")
    if pts.ndim != 2 or pts.shape[1] != len(fields):
        raise ValueError(f"points have shape {pts.shape}, expected (n, {len(fields)}) for fields {fields}")
    step = 8 * len(fields)
    return PointCloud2(
        header=_header(stamp_ns, frame_id),
        height=1,
        width=pts.shape[0],
        fields=_point_fields(tuple(fields)),
        is_bigendian=False,
        point_step=step,
        row_step=step * pts.shape[0],
        data=pts.tobytes(),
        is_dense=True,
    )


def cloud_to_points(msg: PointCloud2, fields: tuple[str, ...] = POINT_FIELDS) -> np.ndarray:
    """PointCloud2 -> ``(width * height, len(fields))`` float64 array; checks the layout."""
    got = tuple(f.name for f in msg.fields)
    if got != tuple(fields):
        raise ValueError(f"state fields = {got}, expected {tuple(fields)}")
    for i, f in enumerate(msg.fields):
        if f.datatype != PointField.FLOAT64 or f.offset != 8 * i or f.count != 1:
            raise ValueError(
                f"state field {f.name!r}: datatype {f.datatype} offset {f.offset} count {f.count}, "
                f"expected FLOAT64 ({PointField.FLOAT64}) at offset {8 * i}, count 1"
            )
    step = 8 * len(fields)
    n = int(msg.width) * int(msg.height)
    if msg.point_step != step or len(msg.data) != n * step:
        raise ValueError(
            f"state point_step = {msg.point_step}, {len(msg.data)} data bytes for {n} points, "
            f"expected point_step {step} and {n * step} bytes"
        )
    dtype = np.dtype(">f8" if msg.is_bigendian else "<f8")
    return np.frombuffer(msg.data, dtype=dtype).astype(np.float64).reshape(n, len(fields))


# -- ego odometry ---------------------------------------------------------------------------------
def make_odometry(
    stamp_ns: int,
    x: float,
    y: float,
    sumo_angle_deg: float,
    speed: float,
    frame_id: str = "map",
    child_frame_id: str = "ego",
) -> Odometry:
    """Ego pose and speed as nav_msgs/Odometry.

    SUMO angles are degrees clockwise from north; ROS (REP 103) yaw is counter-clockwise from
    the x axis (east), so ``yaw = radians(90 - angle)``. The twist is in the child (ego) frame:
    ``linear.x`` is the forward speed.
    """
    msg = Odometry()
    msg.header = _header(stamp_ns, frame_id)
    msg.child_frame_id = child_frame_id
    yaw = math.radians(90.0 - float(sumo_angle_deg))
    msg.pose.pose.position.x = float(x)
    msg.pose.pose.position.y = float(y)
    msg.pose.pose.orientation.z = math.sin(yaw / 2.0)
    msg.pose.pose.orientation.w = math.cos(yaw / 2.0)
    msg.twist.twist.linear.x = float(speed)
    return msg


def odometry_pose(msg: Odometry) -> tuple[int, float, float, float, float]:
    """Inverse of :func:`make_odometry`: (stamp_ns, x, y, sumo_angle_deg in [0, 360), speed)."""
    q = msg.pose.pose.orientation
    yaw = 2.0 * math.atan2(q.z, q.w)
    angle = (90.0 - math.degrees(yaw)) % 360.0
    p = msg.pose.pose.position
    return time_to_ns(msg.header.stamp), p.x, p.y, angle, msg.twist.twist.linear.x


# -- reward ---------------------------------------------------------------------------------------
#: ``reward.header.frame_id`` prefix naming the action the bridge applied to reach this state.
APPLIED_ACTION_PREFIX = "applied_action="


def make_reward(
    stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None
) -> Vector3Stamped:
    """``reward`` message: x = reward on arriving in the state stamped ``stamp_ns``, y/z = flags.

    ``applied_action`` (the action the bridge actually applied in the step that led here: the
    agent's command, or the default after a timeout) goes into ``header.frame_id`` as
    ``applied_action=<a>``; empty for an episode's first state.
    """
    msg = Vector3Stamped()
    frame = "" if applied_action is None else f"{APPLIED_ACTION_PREFIX}{int(applied_action)}"
    msg.header = _header(stamp_ns, frame)
    msg.vector.x = float(reward)
    msg.vector.y = 1.0 if terminated else 0.0
    msg.vector.z = 1.0 if truncated else 0.0
    return msg


def parse_reward(msg: Vector3Stamped) -> tuple[int, float, bool, bool]:
    """``reward`` message -> (stamp_ns, reward, terminated, truncated); ValueError if malformed."""
    v = msg.vector
    if not math.isfinite(v.x):
        raise ValueError(f"reward x = {v.x!r}, expected a finite number")
    for name, flag in (("y (terminated)", v.y), ("z (truncated)", v.z)):
        if flag not in (0.0, 1.0):
            raise ValueError(f"reward {name} = {flag!r}, expected 0 or 1")
    return time_to_ns(msg.header.stamp), float(v.x), v.y == 1.0, v.z == 1.0


def parse_applied_action(msg: Vector3Stamped) -> int | None:
    """The ``applied_action=<a>`` of a reward's frame_id (None when absent); ValueError if garbled."""
    frame = msg.header.frame_id
    if not frame.startswith(APPLIED_ACTION_PREFIX):
        return None
    text = frame[len(APPLIED_ACTION_PREFIX):]
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"reward frame_id = {frame!r}, expected '{APPLIED_ACTION_PREFIX}<integer>'") from None


# -- lane-change command --------------------------------------------------------------------------
def make_command(stamp_ns: int, action: int, sender: str = "") -> Joy:
    """``lane_change_cmd``: header.stamp = stamp of the answered state, buttons[0] = action.

    ``header.frame_id`` carries the sender id the bridge locks onto (rclpy 7.1's MessageInfo
    has no publisher GID; see docs/architecture.md).
    """
    msg = Joy()
    msg.header = _header(stamp_ns, sender)
    msg.buttons = [int(action)]
    return msg


def parse_command(msg: Joy) -> tuple[int, list[int], list[float], str]:
    """``lane_change_cmd`` -> (stamp_ns, buttons, axes, sender); validation is the receiver's job."""
    return time_to_ns(msg.header.stamp), list(msg.buttons), list(msg.axes), msg.header.frame_id


# -- episode events -------------------------------------------------------------------------------
def _kv(values: Mapping[str, object]) -> list[KeyValue]:
    return [KeyValue(key=str(k), value=repr(v) if isinstance(v, float) else str(v)) for k, v in values.items()]


def make_episode_event(
    stamp_ns: int, event: str, values: Mapping[str, object], hardware_id: str = "sumo_bridge"
) -> DiagnosticArray:
    """One ``episode`` status: message = start/success/collision/time_limit, values as key/values.

    A collision is reported at WARN level so generic diagnostics viewers flag it.
    """
    level = DiagnosticStatus.WARN if event == "collision" else DiagnosticStatus.OK
    status = DiagnosticStatus(
        level=level, name=EPISODE_STATUS_NAME, message=event, hardware_id=hardware_id, values=_kv(values)
    )
    return DiagnosticArray(header=_header(stamp_ns, ""), status=[status])


def parse_episode_events(msg: DiagnosticArray) -> list[tuple[int, str, dict[str, float | int | str]]]:
    """Every ``episode`` status of a DiagnosticArray as (stamp_ns, event, values)."""
    stamp = time_to_ns(msg.header.stamp)
    return [
        (stamp, s.message, parse_key_values(s.values))
        for s in msg.status
        if s.name == EPISODE_STATUS_NAME
    ]


# -- metrics --------------------------------------------------------------------------------------
def metrics_to_diagnostics(
    metrics: Mapping[str, float], stamp_ns: int, name: str = METRICS_STATUS_NAME, hardware_id: str = ""
) -> DiagnosticArray:
    """Metrics (stable names such as ``losses/td_loss``) as one DiagnosticStatus of key/values."""
    values = [KeyValue(key=k, value=repr(float(v))) for k, v in metrics.items()]
    status = DiagnosticStatus(level=DiagnosticStatus.OK, name=name, hardware_id=hardware_id, values=values)
    return DiagnosticArray(header=_header(stamp_ns, ""), status=[status])


def diagnostics_to_metrics(msg: DiagnosticArray, names: Sequence[str] | None = None) -> dict[str, float]:
    """Every numeric key/value of the statuses (optionally only those named ``names``) as floats."""
    out: dict[str, float] = {}
    for s in msg.status:
        if names is not None and s.name not in names:
            continue
        for kv in s.values:
            try:
                out[kv.key] = float(kv.value)
            except ValueError:
                continue
    return out
