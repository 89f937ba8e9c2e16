"""The ``/tf`` topic's layout (tf2_msgs/TFMessage): the ``map -> ego`` transform written beside every
``ego/odom``, so that a viewer (Foxglove's 3D panel, RViz) can place the ``state`` cloud (frame
``ego``) in the scene (frame ``map``). Same yaw rule as :mod:`der_ros.contract.odometry`.
"""

from __future__ import annotations

import math
import struct

from der_ros.contract.cdr import ENCAPSULATION, cdr_string, pad, stamp_cdr

__all__ = ["tf_cdr", "ego_tf_cdr"]

_U32 = struct.Struct("<I").pack
_TRANSFORM = struct.Struct("<7d").pack  # translation xyz, rotation xyzw


def tf_cdr(stamp_ns: int, translation: tuple[float, float, float], rotation: tuple[float, float, float, float],
           frame_id: str = "map", child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """tf2_msgs/TFMessage with one TransformStamped ``frame_id -> child_frame_id`` (rotation x, y, z, w)."""
    head = ENCAPSULATION + _U32(1) + stamp_cdr(stamp_ns) + cdr_string(frame_id)
    head += pad(len(head) - 4, 4) + cdr_string(child_frame_id)
    return head + pad(len(head) - 4, 8) + _TRANSFORM(*(float(v) for v in translation), *(float(v) for v in rotation))


def ego_tf_cdr(stamp_ns: int, x: float, y: float, sumo_angle_deg: float, frame_id: str = "map",
               child_frame_id: str = "ego") -> bytes:  # fmt: skip
    """The ``map -> ego`` transform of the ego pose that ``odometry_cdr`` publishes (same yaw rule)."""
    yaw = math.radians(90.0 - float(sumo_angle_deg))
    return tf_cdr(stamp_ns, (x, y, 0.0), (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)), frame_id, child_frame_id)
