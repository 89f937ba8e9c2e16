"""Plain-CDR primitives shared by our hand-written encoders (:mod:`~der_ros.contract`,
:mod:`~der_ros.contract`).

Plain CDR, little endian: a 4-byte encapsulation header, then every field in declaration order,
aligned to its size relative to the end of that header, padding zeroed (what rosbags' serialiser
writes, and what rclpy decodes).
"""

from __future__ import annotations

import struct

__all__ = ["ENCAPSULATION", "NS", "U32", "STAMP", "cdr_string", "pad", "stamp_parts"]

NS = 1_000_000_000  # nanoseconds per second
ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian
U32 = struct.Struct("<I").pack
STAMP = struct.Struct("<iI").pack  # builtin_interfaces/Time: int32 sec, uint32 nanosec


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
