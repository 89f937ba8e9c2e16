"""The ``lane_change_cmd`` topic's layout (sensor_msgs/Joy): ``header.stamp`` = the stamp of the state
it answers, ``buttons = [action]`` (:data:`ACTION_NAMES`), no axes, ``header.frame_id`` = the
sender id the bridge locks onto (rclpy 7.1's MessageInfo has no publisher GID).

Parser of a decoded message (:func:`parse_command`, :func:`command_action`), CDR encoder
(:func:`command_cdr`, the agent node), CDR reader (:func:`read_command_cdr`, the bridge: None for any
other encoding, then rclpy decodes) and the sender read alone (:func:`cdr_command_sender`) side by
side. rclpy's ``deserialize_message`` of a command took ~8 us, building and converting one ~8 us.
"""

from __future__ import annotations

import struct
from typing import Any

from der_ros.contract.cdr import MAX_TRAILING, align, header_cdr, header_ns, pad, read_header_cdr

__all__ = [
    "ACTION_NAMES",
    "parse_command",
    "cdr_command_sender",
    "command_action",
    "command_cdr",
    "read_command_cdr",
]


#: names of the actions ``lane_change_cmd`` carries, by index (the env's ``ACTION_MEANINGS``): 0 keep lane,
#: 1 change left, 2 change right (the paper's set, every scenario's default), 3 faster, 4 slower (the ego's
#: target speed one ``speed_step`` up / down; only in scenarios whose ``actions`` list them). A scenario's
#: set is a prefix of these; the bridge refuses a larger index as OUT_OF_RANGE (counted, sumo_bridge.lockstep).
ACTION_NAMES: tuple[str, ...] = ("keep", "left", "right", "faster", "slower")


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


_U32_AT = struct.Struct("<I").unpack_from
_COMMAND_TAIL = struct.Struct("<IIi").pack  # axes: length 0; buttons: length 1, the action


def command_cdr(stamp_ns: int, action: int, sender: str = "") -> bytes:
    """The ``lane_change_cmd`` (sensor_msgs/Joy) as CDR bytes:
    stamp of the answered state, ``buttons = [action]``, no axes, the sender id in ``header.frame_id``."""
    head = header_cdr(stamp_ns, sender)
    return head + pad(len(head) - 4, 4) + _COMMAND_TAIL(0, 1, int(action))


def read_command_cdr(data: bytes) -> tuple[int, list[int], list[float], str] | None:
    """(stamp ns, buttons, axes, sender) of a ``lane_change_cmd`` Joy in little-endian plain CDR, as
    :func:`parse_command` gives them, or None for any other encoding or a message
    these bytes cannot hold (decode with rclpy then: it rejects what is truly malformed)."""
    head = read_header_cdr(data)
    if head is None:
        return None
    stamp, sender, offset = head
    offset = align(offset, 4)
    if offset + 4 > len(data):
        return None
    (n_axes,) = _U32_AT(data, offset)
    offset += 4
    if offset + 4 * n_axes + 4 > len(data):
        return None
    axes = list(struct.unpack_from(f"<{n_axes}f", data, offset)) if n_axes else []
    offset += 4 * n_axes
    (n_buttons,) = _U32_AT(data, offset)
    offset += 4
    end = offset + 4 * n_buttons
    if not 0 <= len(data) - end <= MAX_TRAILING:
        return None
    buttons = list(struct.unpack_from(f"<{n_buttons}i", data, offset)) if n_buttons else []
    return stamp, buttons, axes, sender
