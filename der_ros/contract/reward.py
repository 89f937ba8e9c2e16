"""The ``reward`` topic's layout (geometry_msgs/Vector3Stamped): x = the reward on arriving in the state
of the same stamp, y/z = terminated/truncated (0 or 1), ``header.frame_id`` = ``applied_action=<a>``,
the action the bridge applied in the step that led here ("" for an episode's first state).

Parser of a decoded message (:func:`parse_reward`), CDR encoder (:func:`reward_cdr`, the bridge) and
CDR reader (:func:`read_reward_cdr`, the agent node: None for any other encoding, then rclpy decodes)
side by side; the reader judges values with the parser's own :func:`reward_from_fields`. rclpy's
``deserialize_message`` of a reward took ~9 us, building and converting one ~15 us; these take a
few us.
"""

from __future__ import annotations

import math
import re
import struct
from typing import Any, NamedTuple

from der_ros.contract.cdr import FLOAT32_MAX, MAX_TRAILING, align, header_cdr, header_ns, pad, read_header_cdr

__all__ = [
    "APPLIED_ACTION_PREFIX",
    "Reward",
    "applied_action_frame",
    "parse_applied_action",
    "parse_reward",
    "reward_from_fields",
    "reward_cdr",
    "read_reward_cdr",
]


#: ``reward.header.frame_id`` = this prefix + the action the bridge applied to reach the state
APPLIED_ACTION_PREFIX = "applied_action="


class Reward(NamedTuple):
    """A parsed ``reward`` message."""

    stamp_ns: int
    reward: float
    terminated: bool
    truncated: bool
    #: the action the bridge applied in the step that led here; None at an episode's first state
    applied_action: int | None


def applied_action_frame(action: int | None) -> str:
    """The ``reward`` frame_id naming the applied action ("" for an episode's first state)."""
    return "" if action is None else f"{APPLIED_ACTION_PREFIX}{int(action)}"


def parse_applied_action(msg: Any) -> int | None:
    """The ``applied_action=<a>`` of a reward's frame_id (None when absent); ValueError if garbled."""
    return _applied_action(str(msg.header.frame_id))


_ACTION_DIGITS = re.compile(r"[0-9]{1,9}")


def _applied_action(frame: str) -> int | None:
    if not frame.startswith(APPLIED_ACTION_PREFIX):
        return None
    digits = frame[len(APPLIED_ACTION_PREFIX):]
    # ASCII digits only: int() also reads '\u0661' (Arabic-Indic one), ' 1', '+1' and '1_0'
    if not _ACTION_DIGITS.fullmatch(digits):
        raise ValueError(f"reward frame_id = {frame[:60]!r}, expected '{APPLIED_ACTION_PREFIX}<integer>' "
                         "(ASCII digits)")
    return int(digits)


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


_VECTOR3 = struct.Struct("<3d").pack
_VECTOR3_AT = struct.Struct("<3d").unpack_from


def reward_cdr(stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None) -> bytes:
    """The ``reward`` message (geometry_msgs/Vector3Stamped) as CDR bytes."""
    head = header_cdr(stamp_ns, applied_action_frame(applied_action))
    return head + pad(len(head) - 4, 8) + _VECTOR3(float(reward), 1.0 if terminated else 0.0, 1.0 if truncated else 0.0)


def read_reward_cdr(data: bytes) -> Reward | None:
    """The :class:`Reward` of a ``reward`` Vector3Stamped in little-endian plain CDR,
    or None for any other encoding. ValueError, as :func:`parse_reward`, for a
    reward or flag out of range or a garbled ``applied_action``."""
    head = read_header_cdr(data)
    if head is None:
        return None
    stamp, frame, offset = head
    offset = align(offset, 8)
    if not 0 <= len(data) - (offset + 24) <= MAX_TRAILING:
        return None
    x, y, z = _VECTOR3_AT(data, offset)
    return reward_from_fields(stamp, frame, x, y, z)
