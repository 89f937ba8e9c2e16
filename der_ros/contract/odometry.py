"""The ``ego/odom`` topic's layout (nav_msgs/Odometry): the ego's pose in the map frame and its forward
speed in its own frame.

SUMO angles are degrees clockwise from north; ROS (REP 103) yaw is counter-clockwise from the x
axis (east): ``yaw = radians(90 - angle)``. Parser (:func:`odometry_pose`) and CDR encoder
(:func:`odometry_cdr`, the bridge; building and converting the rclpy message took ~25 us) side by side.
"""

from __future__ import annotations

import math
import struct
from typing import Any

from der_ros.contract.cdr import align, cdr_string, header_cdr, header_ns, pad, read_header_cdr

__all__ = [
    "odometry_pose",
    "odometry_cdr",
    "read_odometry_pose_cdr",
]



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


_ODOM_POSE = struct.Struct("<7d").pack  # position xyz, orientation xyzw


_COVARIANCE = bytes(36 * 8)


_TWIST = struct.Struct("<6d").pack  # linear xyz, angular xyz


def odometry_cdr(stamp_ns: int, x: float, y: float, sumo_angle_deg: float, speed: float, frame_id: str = "map",
                 child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """The ``ego/odom`` nav_msgs/Odometry as CDR bytes (the yaw rule of :func:`odometry_pose`:
    SUMO degrees clockwise from north -> REP 103 yaw counter-clockwise from east; twist in the child frame)."""
    yaw = math.radians(90.0 - float(sumo_angle_deg))
    head = header_cdr(stamp_ns, frame_id)
    head += pad(len(head) - 4, 4) + cdr_string(child_frame_id)
    pose = _ODOM_POSE(float(x), float(y), 0.0, 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))
    return head + pad(len(head) - 4, 8) + pose + _COVARIANCE + _TWIST(float(speed), 0.0, 0.0, 0.0, 0.0, 0.0) + _COVARIANCE


_POSE = struct.Struct("<7d").unpack_from  # position xyz, orientation xyzw
_U32_AT = struct.Struct("<I").unpack_from


def read_odometry_pose_cdr(data: bytes) -> tuple[int, str, str, tuple[float, ...]] | None:
    """(stamp ns, frame_id, child_frame_id, (x, y, z, qx, qy, qz, qw)) of a little-endian plain-CDR
    nav_msgs/Odometry (the pose only); None if the bytes are not one."""
    head = read_header_cdr(data)
    if head is None:
        return None
    stamp, frame, q = head
    q = align(q, 4)
    if q + 4 > len(data):
        return None
    (length,) = _U32_AT(data, q)
    end = q + 4 + length
    if length < 1 or end > len(data) or data[end - 1] != 0:
        return None
    try:
        child = data[q + 4:end - 1].split(b"\0", 1)[0].decode("utf-8")
    except UnicodeDecodeError:
        return None
    q = align(end, 8)
    if q + 56 > len(data):
        return None
    return stamp, frame, child, _POSE(data, q)
