"""The ``state`` topic's layout (sensor_msgs/PointCloud2): the points of the observation, one row per
point, FLOAT64 fields in order, unordered (height 1), little endian, dense.

Three views of one layout, kept side by side so they cannot drift: :func:`cloud_to_points` reads a
decoded message (rclpy and rosbags alike: attributes only), :func:`state_cdr` writes the CDR bytes
the bridge publishes (``Publisher.publish(bytes)``), :func:`read_state_cdr` reads those bytes back
without rclpy (the agent node) and returns None for any other layout, so the caller decodes with
rclpy then. ``test/contract/test_step_cdr.py`` checks all three against rclpy and rosbags.

Why our own bytes: the state goes out every decision step ahead of the agent's answer, so its cost
is on the lockstep's critical path. Building the rclpy message and letting rclpy convert it took
~40 us (its twelve PointField objects alone ~10 us), rclpy's ``deserialize_message`` ~26 us plus
~8 us for ``cloud_to_points``; the encoder and the reader take a few us each (2-core machine,
``bench/graph.py`` times the graph). The parts that never change (the field table) are laid out once.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from functools import lru_cache
from typing import Any

import numpy as np

from der_ros.contract.cdr import (
    ENCAPSULATION,
    FLOAT32_MAX,
    MAX_TRAILING,
    U32,
    align,
    cdr_string,
    pad,
    read_header_cdr,
    stamp_cdr,
)

__all__ = [
    "POINTFIELD_FLOAT64",
    "point_field_names",
    "cloud_to_points",
    "points_from_buffer",
    "state_field_table",
    "state_cdr",
    "read_state_cdr",
]


#: ``sensor_msgs/PointField.FLOAT64``: the only datatype of the ``state`` cloud's fields
POINTFIELD_FLOAT64 = 8


def point_field_names(msg: Any) -> tuple[str, ...]:
    """Names of the fields of a PointCloud2, in order."""
    return tuple(str(f.name) for f in msg.fields)


def cloud_to_points(msg: Any, fields: Sequence[str] | None = None) -> np.ndarray:
    """``state`` PointCloud2 -> ``(width * height, n_fields)`` float64 array, bit-exact.

    Every field must be FLOAT64, count 1, packed in order (the bridge's layout); ``fields``
    (e.g. ``observation.POINT_FIELDS``) also pins the names; every value must be finite and
    within float32's range (the simulator never sends others; a NaN would poison the replay).
    Anything else raises ValueError naming the field: a silently re-typed observation would break
    the promise that the agent, the environment and the export see bit-identical observations.
    """
    names = point_field_names(msg)
    if fields is not None and names != tuple(fields):
        raise ValueError(f"state fields = {names}, expected {tuple(fields)}")
    for i, f in enumerate(msg.fields):
        if f.datatype != POINTFIELD_FLOAT64 or f.offset != 8 * i or f.count != 1:
            raise ValueError(
                f"state field {f.name!r}: datatype {f.datatype} offset {f.offset} count {f.count}, "
                f"expected FLOAT64 ({POINTFIELD_FLOAT64}) at offset {8 * i}, count 1"
            )
    step = 8 * len(names)
    n = int(msg.width) * int(msg.height)
    data = msg.data
    if int(msg.point_step) != step or len(data) != n * step:
        raise ValueError(
            f"state point_step = {msg.point_step}, {len(data)} data bytes for {n} points, "
            f"expected point_step {step} and {n * step} bytes"
        )
    return points_from_buffer(data, n, names, bool(msg.is_bigendian))


def points_from_buffer(data: Any, n: int, names: Sequence[str], bigendian: bool = False) -> np.ndarray:
    """The ``(n, len(names))`` float64 points of a ``state``'s data bytes (FLOAT64 fields in order), a
    copy; ValueError naming the point and field of a value that is not finite or beyond float32's range.
    The last step of :func:`cloud_to_points`, shared with the CDR reader of the agent node
    (:func:`read_state_cdr`), which has checked the rest of the layout itself."""
    dtype = np.dtype(">f8" if bigendian else "<f8")
    # rclpy gives array.array/bytes, rosbags a uint8 ndarray: all expose the buffer protocol
    points = np.frombuffer(data, dtype=dtype).astype(np.float64).reshape(n, len(names))
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(points) | (np.abs(points) > FLOAT32_MAX)
    if bad.any():  # a NaN/inf point would reach the observation (and the replay) of every consumer
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"state point {row} field {names[col]!r} = {points[row, col]!r}, expected a finite number "
                         "within float32 range")
    return points


class _Layout:
    """Bytes with their CDR offset tracked (counted after the encapsulation), for the constant parts."""

    def __init__(self, offset: int) -> None:
        self.offset = offset
        self.out = bytearray()

    def put(self, data: bytes, align: int = 1) -> None:
        gap = pad(self.offset, align)
        self.out += gap + data
        self.offset += len(gap) + len(data)


@lru_cache(maxsize=8)
def _state_parts(frame_id: str, fields: tuple[str, ...]) -> tuple[bytes, bytes]:
    """The constant bytes of a state: (header frame + height, up to ``width``; the field table and
    is_bigendian after it, padded for ``point_step``). Every offset before the data is fixed."""
    head = _Layout(8)  # after the stamp
    head.put(cdr_string(frame_id), 4)
    head.put(U32(1), 4)  # height: an unordered cloud
    mid = _Layout(head.offset + 4)  # after width (uint32, aligned: height was)
    mid.put(U32(len(fields)), 4)
    for i, name in enumerate(fields):
        mid.put(cdr_string(name), 4)
        mid.put(U32(8 * i), 4)  # offset
        mid.put(bytes([POINTFIELD_FLOAT64]))  # datatype
        mid.put(U32(1), 4)  # count
    mid.put(b"\0")  # is_bigendian
    mid.put(b"", 4)  # point_step follows
    return bytes(head.out), bytes(mid.out)


def state_field_table(fields: tuple[str, ...]) -> bytes:
    """The constant bytes of a state between ``width`` and ``point_step`` (the field table, is_bigendian
    and padding), the same for every frame_id: they start 4-aligned and align to at most 4."""
    return _state_parts("", tuple(fields))[1]


_CLOUD_SIZES = struct.Struct("<III").pack  # point_step, row_step, len(data)


def state_cdr(points: np.ndarray, stamp_ns: int, frame_id: str = "ego", *, fields: tuple[str, ...]) -> bytes:
    """The ``state`` PointCloud2 as CDR bytes (FLOAT64 fields, unordered, little endian, dense). ``fields`` names the columns (the bridge's
    :data:`sumo_bridge.observation.POINT_FIELDS`): the contract does not depend on the simulator."""
    pts = np.ascontiguousarray(points, dtype="<f8")
    if pts.ndim != 2 or pts.shape[1] != len(fields):
        raise ValueError(f"points have shape {pts.shape}, expected (n, {len(fields)}) for fields {fields}")
    head, mid = _state_parts(frame_id, tuple(fields))
    step = 8 * len(fields)
    data = pts.tobytes()
    return b"".join((ENCAPSULATION, stamp_cdr(stamp_ns), head, U32(pts.shape[0]), mid,
                     _CLOUD_SIZES(step, step * pts.shape[0], len(data)), data, b"\x01"))  # fmt: skip


_U32X2 = struct.Struct("<II").unpack_from
_U32X3 = struct.Struct("<III").unpack_from


def read_state_cdr(data: bytes, fields: tuple[str, ...]) -> tuple[int, np.ndarray] | None:
    """(stamp ns, points) of a ``state`` PointCloud2 laid out as :func:`state_cdr`
    writes it with these ``fields``, or None for any other layout (decode with rclpy then). ValueError,
    as :func:`cloud_to_points`, for a point that is not finite or beyond float32."""
    head = read_header_cdr(data)
    if head is None:
        return None
    stamp, _frame, offset = head
    offset = align(offset, 4)
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
    if point_step != step or size != n * step or not 0 <= len(data) - end <= MAX_TRAILING:
        return None
    return stamp, points_from_buffer(memoryview(data)[start:start + size], n, fields)
