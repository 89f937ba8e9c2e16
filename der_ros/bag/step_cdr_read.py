"""Reading the per-step messages straight from their CDR bytes, without rclpy: ``state`` and ``reward``
(the agent node), ``lane_change_cmd`` (the bridge node).

The other half of :mod:`der_ros.bag.step_cdr`. Each reader takes the bytes a raw subscription hands
over and returns what the contract's parser (:mod:`der_ros.contract`) returns for the decoded message,
or **None when the bytes are not laid out the way our encoders write them** (big-endian or XCDR2
encapsulation, another field table, a truncated or padded message): the caller then decodes them with
rclpy and the contract's parser, which accepts every valid encoding and names what is wrong with an
invalid one. So the fast path never accepts what the general one would reject: values are checked by
the same functions (:func:`~der_ros.contract.points_from_buffer`,
:func:`~der_ros.contract.reward_from_fields`), and ``test/test_step_cdr.py`` checks that both paths
agree on every message of our encoders and on corrupted ones.

Why: in lockstep the state, the reward and the command are on the round trip's critical path. rclpy's
``deserialize_message`` of the state (twelve PointField objects) took ~26 us plus ~8 us for
``cloud_to_points``, the reward ~9 us, the command ~8 us, and building + converting the command ~8 us;
these readers take a few us each (2-core machine, ``bench/graph.py`` times the whole graph).
"""

from __future__ import annotations

import struct

import numpy as np

from der_ros.bag.cdr import ENCAPSULATION
from der_ros.bag.cdr import NS as _NS
from der_ros.bag.step_cdr import state_field_table
from der_ros.contract import Reward, points_from_buffer, reward_from_fields

__all__ = ["read_state_cdr", "read_reward_cdr", "read_command_cdr", "read_odometry_pose_cdr"]

_STAMP_LEN = struct.Struct("<iII").unpack_from  # sec, nanosec, length of frame_id (with its NUL)
_U32 = struct.Struct("<I").unpack_from
_U32X2 = struct.Struct("<II").unpack_from
_U32X3 = struct.Struct("<III").unpack_from
_VECTOR3 = struct.Struct("<3d").unpack_from
#: bytes a serialiser may add after the last member (alignment of the whole message to 4)
_MAX_TRAILING = 3


def _header(data: bytes) -> tuple[int, str, int] | None:
    """(stamp ns, frame_id, offset after it) of a little-endian plain-CDR message with a Header first."""
    if len(data) < 16 or data[:4] != ENCAPSULATION:
        return None
    sec, nanosec, length = _STAMP_LEN(data, 4)
    end = 16 + length
    if length < 1 or end > len(data) or data[end - 1] != 0:
        return None
    raw = data[16:end - 1]
    nul = raw.find(b"\0")
    if nul >= 0:  # rclpy's strings end at the first NUL, whatever the length says
        raw = raw[:nul]
    try:
        frame = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    return sec * _NS + nanosec, frame, end


def _align(offset: int, n: int) -> int:
    """``offset`` (from the start of the bytes) moved up to a multiple of ``n`` counted after the encapsulation."""
    return offset + (-(offset - 4) % n)


def read_state_cdr(data: bytes, fields: tuple[str, ...]) -> tuple[int, np.ndarray] | None:
    """(stamp ns, points) of a ``state`` PointCloud2 laid out as :func:`~der_ros.bag.step_cdr.state_cdr`
    writes it with these ``fields``, or None for any other layout (decode with rclpy then). ValueError,
    as :func:`~der_ros.contract.cloud_to_points`, for a point that is not finite or beyond float32."""
    head = _header(data)
    if head is None:
        return None
    stamp, _frame, offset = head
    offset = _align(offset, 4)
    table = state_field_table(fields)
    end_table = offset + 8 + len(table)
    if end_table + 12 > len(data) or data[offset + 8:end_table] != table:
        return None
    height, width = _U32X2(data, offset)
    point_step, _row_step, size = _U32X3(data, end_table)
    n = height * width
    start = end_table + 12
    step = 8 * len(fields)
    end = start + size + 1  # is_dense follows the data
    if point_step != step or size != n * step or not 0 <= len(data) - end <= _MAX_TRAILING:
        return None
    return stamp, points_from_buffer(memoryview(data)[start:start + size], n, fields)


def read_reward_cdr(data: bytes) -> Reward | None:
    """The :class:`~der_ros.contract.Reward` of a ``reward`` Vector3Stamped in little-endian plain CDR,
    or None for any other encoding. ValueError, as :func:`~der_ros.contract.parse_reward`, for a
    reward or flag out of range or a garbled ``applied_action``."""
    head = _header(data)
    if head is None:
        return None
    stamp, frame, offset = head
    offset = _align(offset, 8)
    if not 0 <= len(data) - (offset + 24) <= _MAX_TRAILING:
        return None
    x, y, z = _VECTOR3(data, offset)
    return reward_from_fields(stamp, frame, x, y, z)


def read_command_cdr(data: bytes) -> tuple[int, list[int], list[float], str] | None:
    """(stamp ns, buttons, axes, sender) of a ``lane_change_cmd`` Joy in little-endian plain CDR, as
    :func:`~der_ros.contract.parse_command` gives them, or None for any other encoding or a message
    these bytes cannot hold (decode with rclpy then: it rejects what is truly malformed)."""
    head = _header(data)
    if head is None:
        return None
    stamp, sender, offset = head
    offset = _align(offset, 4)
    if offset + 4 > len(data):
        return None
    (n_axes,) = _U32(data, offset)
    offset += 4
    if offset + 4 * n_axes + 4 > len(data):
        return None
    axes = list(struct.unpack_from(f"<{n_axes}f", data, offset)) if n_axes else []
    offset += 4 * n_axes
    (n_buttons,) = _U32(data, offset)
    offset += 4
    end = offset + 4 * n_buttons
    if not 0 <= len(data) - end <= _MAX_TRAILING:
        return None
    buttons = list(struct.unpack_from(f"<{n_buttons}i", data, offset)) if n_buttons else []
    return stamp, buttons, axes, sender


_POSE = struct.Struct("<7d").unpack_from  # position xyz, orientation xyzw


def read_odometry_pose_cdr(data: bytes) -> tuple[int, str, str, tuple[float, ...]] | None:
    """(stamp ns, frame_id, child_frame_id, (x, y, z, qx, qy, qz, qw)) of a little-endian plain-CDR
    nav_msgs/Odometry (the pose only); None if the bytes are not one."""
    head = _header(data)
    if head is None:
        return None
    stamp, frame, q = head
    q = _align(q, 4)
    if q + 4 > len(data):
        return None
    (length,) = _U32(data, q)
    end = q + 4 + length
    if length < 1 or end > len(data) or data[end - 1] != 0:
        return None
    try:
        child = data[q + 4:end - 1].split(b"\0", 1)[0].decode("utf-8")
    except UnicodeDecodeError:
        return None
    q = _align(end, 8)
    if q + 56 > len(data):
        return None
    return stamp, frame, child, _POSE(data, q)
