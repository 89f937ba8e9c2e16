"""Builders of the graph's rclpy messages from core data (numpy arrays, dicts, nanoseconds).

The layouts are the graph contract (:mod:`der_ros.contract`); the parsers that read them back
live there too, ROS-free, so offline tools and the nodes decode with the same code. Every
function here is pure (no node, no clock), so round trips are unit-testable.

Hot-path notes: the PointCloud2 field layout is computed once per field tuple (cached), the
payload is ``ndarray.tobytes()`` (no per-point Python loop).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import lru_cache

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2, PointField
from std_msgs.msg import Header

from der_ros.contract import (
    EPISODE_COLLISION,
    EPISODE_STATUS,
    METRICS_STATUS,
    SAFETY_STATUS,
    applied_action_frame,
    format_value,
)
from sumo_bridge.observation import POINT_FIELDS

__all__ = [
    "ns_to_time",
    "make_clock",
    "points_to_cloud",
    "make_odometry",
    "make_reward",
    "make_command",
    "make_episode_event",
    "make_diagnostics",
    "make_safety_record",
    "metrics_to_diagnostics",
]

_NS_PER_S = 1_000_000_000


# -- time -----------------------------------------------------------------------------------------
def ns_to_time(ns: int) -> Time:
    """Nanoseconds (>= 0) -> builtin_interfaces/Time."""
    ns = int(ns)
    if ns < 0:
        raise ValueError(f"time = {ns} ns, expected >= 0")
    sec, nanosec = divmod(ns, _NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


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


# -- reward ---------------------------------------------------------------------------------------
def make_reward(
    stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None
) -> Vector3Stamped:
    """``reward`` message: x = reward on arriving in the state stamped ``stamp_ns``, y/z = flags.

    ``applied_action`` (the action the bridge actually applied in the step that led here: the
    agent's command, or the default after a timeout) goes into ``header.frame_id`` as
    ``applied_action=<a>`` (:func:`der_ros.contract.applied_action_frame`); empty for an episode's
    first state.
    """
    msg = Vector3Stamped()
    msg.header = _header(stamp_ns, applied_action_frame(applied_action))
    msg.vector.x = float(reward)
    msg.vector.y = 1.0 if terminated else 0.0
    msg.vector.z = 1.0 if truncated else 0.0
    return msg


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


# -- episode events -------------------------------------------------------------------------------
def _kv(values: Mapping[str, object]) -> list[KeyValue]:
    return [KeyValue(key=str(k), value=format_value(v)) for k, v in values.items()]


def make_episode_event(
    stamp_ns: int, event: str, values: Mapping[str, object], hardware_id: str = "sumo_bridge"
) -> DiagnosticArray:
    """One ``episode`` status: message = start/success/collision/time_limit, values as key/values.

    A collision is reported at WARN level so generic diagnostics viewers flag it.
    """
    level = DiagnosticStatus.WARN if event == EPISODE_COLLISION else DiagnosticStatus.OK
    status = DiagnosticStatus(
        level=level, name=EPISODE_STATUS, message=event, hardware_id=hardware_id, values=_kv(values)
    )
    return DiagnosticArray(header=_header(stamp_ns, ""), status=[status])


# -- metrics --------------------------------------------------------------------------------------
def metrics_to_diagnostics(
    metrics: Mapping[str, float], stamp_ns: int, name: str = METRICS_STATUS, hardware_id: str = ""
) -> DiagnosticArray:
    """Metrics (stable names such as ``losses/td_loss``) as one DiagnosticStatus of key/values."""
    return make_diagnostics(stamp_ns, name, metrics, hardware_id=hardware_id)


def make_diagnostics(
    stamp_ns: int, name: str, values: Mapping[str, float], *, message: str = "", hardware_id: str = "", warn: bool = False
) -> DiagnosticArray:
    """One status of numeric key/values (``repr`` floats), WARN level when ``warn``."""
    status = DiagnosticStatus(
        level=DiagnosticStatus.WARN if warn else DiagnosticStatus.OK, name=name, message=message,
        hardware_id=hardware_id, values=[KeyValue(key=k, value=repr(float(v))) for k, v in values.items()],
    )
    return DiagnosticArray(header=_header(stamp_ns, ""), status=[status])


# -- safety records -------------------------------------------------------------------------------
def make_safety_record(stamp_ns: int, verdict: str, proposed: int, applied: int, interventions: int) -> DiagnosticArray:
    """One ``safety/interventions`` record: message = verdict, values proposed / applied / interventions so far
    (:func:`der_ros.contract.parse_safety_record` reads it back); WARN level when the command was changed."""
    values = [KeyValue(key="proposed", value=str(int(proposed))), KeyValue(key="applied", value=str(int(applied))),
              KeyValue(key="interventions", value=str(int(interventions)))]  # fmt: skip
    level = DiagnosticStatus.WARN if applied != proposed else DiagnosticStatus.OK
    status = DiagnosticStatus(level=level, name=SAFETY_STATUS, message=verdict, values=values)
    return DiagnosticArray(header=_header(stamp_ns, ""), status=[status])
