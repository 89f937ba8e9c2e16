"""Plain-CDR primitives and the ``std_msgs/Header`` every message of the graph starts with.

Shared by the per-message modules of the contract (:mod:`~der_ros.contract.state`,
:mod:`~der_ros.contract.reward`, :mod:`~der_ros.contract.command`, :mod:`~der_ros.contract.odometry`,
:mod:`~der_ros.contract.scene`): the header as bytes (:func:`header_cdr`, :func:`read_header_cdr`) and
as the attributes of a decoded message (:func:`stamp_to_ns`, :func:`header_ns`), and ``/clock``,
which is a stamp alone.

Plain CDR, little endian: a 4-byte encapsulation header, then every field in declaration order,
aligned to its size relative to the end of that header, padding zeroed (what rosbags' serialiser
writes, and what rclpy decodes).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

__all__ = ["ENCAPSULATION", "NS", "U32", "STAMP", "FLOAT32_MAX", "MAX_TRAILING", "cdr_string", "pad", "align",
           "stamp_parts", "stamp_cdr", "header_cdr", "read_header_cdr", "clock_cdr", "stamp_to_ns", "header_ns"]

NS = 1_000_000_000  # nanoseconds per second
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian
U32 = struct.Struct("<I").pack
STAMP = struct.Struct("<iI").pack  # builtin_interfaces/Time: int32 sec, uint32 nanosec
#: observations and rewards are stored as float32: larger values (and NaN/inf) are malformed input
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: bytes a serialiser may add after the last member (alignment of the whole message to 4)
MAX_TRAILING = 3


def cdr_string(text: str) -> bytes:
    """A CDR string: length with the terminating NUL, the UTF-8 bytes, the NUL."""
    data = text.encode()
    return U32(len(data) + 1) + data + b"\0"


def pad(offset: int, n: int) -> bytes:
    """Zero bytes that align ``offset`` (counted after the encapsulation) to a multiple of ``n``."""
    return bytes(-offset % n)


def stamp_parts(stamp_ns: int, what: str = "time") -> tuple[int, int]:
    """(sec, nanosec) of a non-negative time in ns; ValueError naming ``what`` otherwise."""
    ns = int(stamp_ns)
    if ns < 0:
        raise ValueError(f"{what} = {ns} ns, expected >= 0")
    return divmod(ns, NS)


def stamp_cdr(stamp_ns: int) -> bytes:
    """``builtin_interfaces/Time`` of ``stamp_ns`` as CDR bytes."""
    return STAMP(*stamp_parts(stamp_ns))


def header_cdr(stamp_ns: int, frame_id: str) -> bytes:
    """Encapsulation + std_msgs/Header (the first member of each message of the graph)."""
    return ENCAPSULATION + stamp_cdr(stamp_ns) + cdr_string(frame_id)


def clock_cdr(stamp_ns: int) -> bytes:
    """rosgraph_msgs/Clock at ``stamp_ns``."""
    return ENCAPSULATION + stamp_cdr(stamp_ns)


_STAMP_LEN = struct.Struct("<iII").unpack_from  # sec, nanosec, length of frame_id (with its NUL)


def read_header_cdr(data: bytes) -> tuple[int, str, int] | None:
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
    return sec * NS + nanosec, frame, end


def align(offset: int, n: int) -> int:
    """``offset`` (from the start of the bytes) moved up to a multiple of ``n`` counted after the encapsulation."""
    return offset + (-(offset - 4) % n)


def stamp_to_ns(t: Any) -> int:
    """``builtin_interfaces/Time`` -> nanoseconds (the step key of the graph)."""
    return int(t.sec) * NS + int(t.nanosec)


def header_ns(msg: Any) -> int:
    """The header stamp of a message in nanoseconds."""
    return stamp_to_ns(msg.header.stamp)
