"""The per-step messages (``/clock``, ``reward``, ``state``, ``ego/odom``, the agent's ``lane_change_cmd``) as CDR bytes, without ROS.

Like :mod:`der_ros.bag.scene_cdr`: ``Publisher.publish(bytes)`` sends them as they are. Plain CDR,
little endian (encapsulation ``00 01 00 00``), every field in declaration order, aligned to its size
relative to the end of the encapsulation header, padding zeroed: rosbags' serialiser gives the same
bytes, and rclpy decodes them into the same messages as the builders of
:mod:`der_ros.nodes.msg_conversions` make (``test/test_step_cdr.py`` checks both, for every field).
What the messages mean is the contract's (:mod:`der_ros.contract`).

Why: these four go out every decision step, three of them ahead of the agent's answer, so their
cost is on the lockstep's critical path. Building the rclpy messages and letting rclpy convert them
took ~40 us for the state (its twelve PointField objects alone ~10 us), ~15 us for the reward and
~25 us for the odometry; these encoders take a few us each (``bench/graph.py`` times the graph).
The parts that never change (the state's field table, the odometry's covariances) are laid out once.
The agent's answer, ``lane_change_cmd``, is on the same path the other way (:func:`command_cdr`).
Reading them back without rclpy: :mod:`der_ros.bag.step_cdr_read`.
"""

from __future__ import annotations

import math
import struct
from functools import lru_cache

import numpy as np

from der_ros.bag.cdr import ENCAPSULATION as _ENCAPSULATION
from der_ros.bag.cdr import STAMP as _STAMP
from der_ros.bag.cdr import U32 as _U32
from der_ros.bag.cdr import cdr_string as _string
from der_ros.bag.cdr import pad as _pad
from der_ros.bag.cdr import stamp_parts
from der_ros.contract import applied_action_frame
from sumo_bridge.observation import POINT_FIELDS

__all__ = ["clock_cdr", "command_cdr", "reward_cdr", "state_cdr", "state_field_table", "odometry_cdr", "tf_cdr", "ego_tf_cdr"]

_FLOAT64 = 8  # sensor_msgs/PointField.FLOAT64


def _stamp(stamp_ns: int) -> bytes:
    return _STAMP(*stamp_parts(stamp_ns))


def _header(stamp_ns: int, frame_id: str) -> bytes:
    """Encapsulation + std_msgs/Header (the first member of each of these messages)."""
    return _ENCAPSULATION + _stamp(stamp_ns) + _string(frame_id)


def clock_cdr(stamp_ns: int) -> bytes:
    """rosgraph_msgs/Clock at ``stamp_ns``."""
    return _ENCAPSULATION + _stamp(stamp_ns)


_VECTOR3 = struct.Struct("<3d").pack


def reward_cdr(stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None) -> bytes:
    """The ``reward`` message (geometry_msgs/Vector3Stamped) of :func:`der_ros.nodes.msg_conversions.make_reward`."""
    head = _header(stamp_ns, applied_action_frame(applied_action))
    return head + _pad(len(head) - 4, 8) + _VECTOR3(float(reward), 1.0 if terminated else 0.0, 1.0 if truncated else 0.0)


_COMMAND_TAIL = struct.Struct("<IIi").pack  # axes: length 0; buttons: length 1, the action


def command_cdr(stamp_ns: int, action: int, sender: str = "") -> bytes:
    """The ``lane_change_cmd`` (sensor_msgs/Joy) of :func:`der_ros.nodes.msg_conversions.make_command`:
    stamp of the answered state, ``buttons = [action]``, no axes, the sender id in ``header.frame_id``."""
    head = _header(stamp_ns, sender)
    return head + _pad(len(head) - 4, 4) + _COMMAND_TAIL(0, 1, int(action))


class _Layout:
    """Bytes with their CDR offset tracked (counted after the encapsulation), for the constant parts."""

    def __init__(self, offset: int) -> None:
        self.offset = offset
        self.out = bytearray()

    def put(self, data: bytes, align: int = 1) -> None:
        pad = _pad(self.offset, align)
        self.out += pad + data
        self.offset += len(pad) + len(data)


@lru_cache(maxsize=8)
def _state_parts(frame_id: str, fields: tuple[str, ...]) -> tuple[bytes, bytes]:
    """The constant bytes of a state: (header frame + height, up to ``width``; the field table and
    is_bigendian after it, padded for ``point_step``). Every offset before the data is fixed."""
    head = _Layout(8)  # after the stamp
    head.put(_string(frame_id), 4)
    head.put(_U32(1), 4)  # height: an unordered cloud
    mid = _Layout(head.offset + 4)  # after width (uint32, aligned: height was)
    mid.put(_U32(len(fields)), 4)
    for i, name in enumerate(fields):
        mid.put(_string(name), 4)
        mid.put(_U32(8 * i), 4)  # offset
        mid.put(bytes([_FLOAT64]))  # datatype
        mid.put(_U32(1), 4)  # count
    mid.put(b"\0")  # is_bigendian
    mid.put(b"", 4)  # point_step follows
    return bytes(head.out), bytes(mid.out)


def state_field_table(fields: tuple[str, ...] = POINT_FIELDS) -> bytes:
    """The constant bytes of a state between ``width`` and ``point_step`` (the field table, is_bigendian
    and padding), the same for every frame_id: they start 4-aligned and align to at most 4."""
    return _state_parts("", tuple(fields))[1]


_CLOUD_SIZES = struct.Struct("<III").pack  # point_step, row_step, len(data)


def state_cdr(points: np.ndarray, stamp_ns: int, frame_id: str = "ego", fields: tuple[str, ...] = POINT_FIELDS) -> bytes:
    """The ``state`` PointCloud2 of :func:`der_ros.nodes.msg_conversions.points_to_cloud` (FLOAT64 fields,
    unordered, little endian, dense)."""
    pts = np.ascontiguousarray(points, dtype="<f8")
    if pts.ndim != 2 or pts.shape[1] != len(fields):
        raise ValueError(f"points have shape {pts.shape}, expected (n, {len(fields)}) for fields {fields}")
    head, mid = _state_parts(frame_id, tuple(fields))
    step = 8 * len(fields)
    data = pts.tobytes()
    return b"".join((_ENCAPSULATION, _stamp(stamp_ns), head, _U32(pts.shape[0]), mid,
                     _CLOUD_SIZES(step, step * pts.shape[0], len(data)), data, b"\x01"))  # fmt: skip


_ODOM_POSE = struct.Struct("<7d").pack  # position xyz, orientation xyzw
_COVARIANCE = bytes(36 * 8)
_TWIST = struct.Struct("<6d").pack  # linear xyz, angular xyz


def odometry_cdr(stamp_ns: int, x: float, y: float, sumo_angle_deg: float, speed: float, frame_id: str = "map",
                 child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """The ``ego/odom`` nav_msgs/Odometry of :func:`der_ros.nodes.msg_conversions.make_odometry` (same yaw rule:
    SUMO degrees clockwise from north -> REP 103 yaw counter-clockwise from east; twist in the child frame)."""
    yaw = math.radians(90.0 - float(sumo_angle_deg))
    head = _header(stamp_ns, frame_id)
    head += _pad(len(head) - 4, 4) + _string(child_frame_id)
    pose = _ODOM_POSE(float(x), float(y), 0.0, 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))
    return head + _pad(len(head) - 4, 8) + pose + _COVARIANCE + _TWIST(float(speed), 0.0, 0.0, 0.0, 0.0, 0.0) + _COVARIANCE


def tf_cdr(stamp_ns: int, translation: tuple[float, float, float], rotation: tuple[float, float, float, float],
           frame_id: str = "map", child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """tf2_msgs/TFMessage with one TransformStamped ``frame_id -> child_frame_id`` (rotation x, y, z, w)."""
    head = _ENCAPSULATION + _U32(1) + _stamp(stamp_ns) + _string(frame_id)
    head += _pad(len(head) - 4, 4) + _string(child_frame_id)
    return head + _pad(len(head) - 4, 8) + _ODOM_POSE(*(float(v) for v in translation), *(float(v) for v in rotation))


def ego_tf_cdr(stamp_ns: int, x: float, y: float, sumo_angle_deg: float, frame_id: str = "map",
               child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """The ``map -> ego`` transform of the ego pose :func:`odometry_cdr` publishes (same yaw rule)."""
    yaw = math.radians(90.0 - float(sumo_angle_deg))
    return tf_cdr(stamp_ns, (x, y, 0.0), (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)), frame_id, child_frame_id)
