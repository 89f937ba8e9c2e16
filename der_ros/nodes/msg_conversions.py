"""Builders of the graph's rclpy messages from core data (numpy arrays, dicts, nanoseconds).

The layouts are the graph contract's (:mod:`der_ros.contract`), spelled there once: the state,
odometry, reward, command and clock built here are rclpy's decoding of the contract's own CDR
bytes; the episode events and metrics (DiagnosticArray) are built from the contract's key/values
(:func:`der_ros.contract.format_value`). Every function here is pure (no node, no clock), so round
trips are unit-testable.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2
from std_msgs.msg import Header

from der_ros.contract import (
    EPISODE_COLLISION,
    EPISODE_STATUS,
    METRICS_STATUS,
    SAFETY_STATUS,
    clock_cdr,
    command_cdr,
    format_value,
    odometry_cdr,
    reward_cdr,
    state_cdr,
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
    return deserialize_message(clock_cdr(stamp_ns), Clock)


# -- state, ego odometry, reward, command: decoded from the contract's own bytes ----------------------
# The layouts are spelled once, in der_ros.contract (state, odometry, reward, command): these builders
# hand rclpy the bytes of the contract's encoders, so an rclpy message built here is by construction
# what the bridge and the agent publish. Not on any hot path (the nodes publish the bytes themselves).
def points_to_cloud(
    points: np.ndarray, stamp_ns: int, frame_id: str = "ego", fields: tuple[str, ...] = POINT_FIELDS
) -> PointCloud2:
    """A ``(n, len(fields))`` float64 array -> an unordered (height 1) PointCloud2, little endian
    (:func:`der_ros.contract.state_cdr`)."""
    return deserialize_message(state_cdr(points, stamp_ns, frame_id, fields=tuple(fields)), PointCloud2)


def make_odometry(
    stamp_ns: int,
    x: float,
    y: float,
    sumo_angle_deg: float,
    speed: float,
    frame_id: str = "map",
    child_frame_id: str = "ego",
) -> Odometry:
    """Ego pose and speed as nav_msgs/Odometry (:func:`der_ros.contract.odometry_cdr`: SUMO degrees
    clockwise from north -> REP 103 yaw counter-clockwise from east; twist in the ego's frame)."""
    return deserialize_message(odometry_cdr(stamp_ns, x, y, sumo_angle_deg, speed, frame_id, child_frame_id), Odometry)


def make_reward(
    stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None
) -> Vector3Stamped:
    """``reward`` message (:func:`der_ros.contract.reward_cdr`): x = reward on arriving in the state
    stamped ``stamp_ns``, y/z = flags, ``header.frame_id`` = the applied action ("" for an episode's
    first state)."""
    return deserialize_message(reward_cdr(stamp_ns, reward, terminated, truncated, applied_action), Vector3Stamped)


def make_command(stamp_ns: int, action: int, sender: str = "") -> Joy:
    """``lane_change_cmd`` (:func:`der_ros.contract.command_cdr`): header.stamp = stamp of the answered
    state, buttons[0] = action, ``header.frame_id`` = the sender id the bridge locks onto."""
    return deserialize_message(command_cdr(stamp_ns, action, sender), Joy)


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
