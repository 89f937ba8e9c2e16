"""The scene marker arrays (``scene/vehicles``, ``scene/road``) as CDR bytes, without ROS.

One encoder serves the bridge node (``Publisher.publish(bytes)`` publishes them as they are) and
the offline tools (``BagWriter.write`` stores them as they are), so a live scene and a recorded one
are the same bytes. The layout is ``visualization_msgs/msg/MarkerArray`` of ROS 2 Jazzy in plain
CDR, little endian (encapsulation ``00 01 00 00``), every field in declaration order, aligned to its
size relative to the end of the encapsulation header, padding zeroed: what rosbags' serialiser
produces, byte for byte, and what rclpy decodes into the same message (Fast CDR leaves padding
bytes unset, so its own bytes differ there only; ``test/sumo/test_scene.py`` checks both). What a marker
means is the contract's
(:mod:`der_ros.contract`: namespaces, roles, colours); :func:`der_ros.contract.parse_vehicle_markers`
reads them back from rclpy and rosbags messages alike: meaning, parsers and encoders are this one module.

Why our own encoder (measured, not assumed): building the array of 25 ring vehicles as rclpy
messages and converting them for publishing took ~1,000-1,400 us per step, with rosbags'
``serialize_cdr`` ~1,700 us; this encoder takes ~70-120 us (same process, loaded 2-core machine),
and the bridge does it every decision step next to SUMO's own few ms. The urban scene has ~220
vehicles. The parts of a vehicle's marker that never change are laid out once (``_ROLE_TAIL``...).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np

from der_ros.contract.cdr import ENCAPSULATION as _ENCAPSULATION
from der_ros.contract.cdr import NS as _NS
from der_ros.contract.cdr import STAMP as _STAMP
from der_ros.contract.cdr import U32 as _U32
from der_ros.contract.cdr import cdr_string as _string
from der_ros.contract.cdr import header_ns, stamp_parts

__all__ = [
    "MARKER_CUBE", "MARKER_LINE_STRIP", "MARKER_ADD", "MARKER_DELETE", "MARKER_DELETEALL", "VEHICLE_NS", "LANE_NS",
    "VEHICLE_HEIGHT", "SCENE_ROLES", "EGO_ROLE", "TRAFFIC_ROLE", "ROLE_COLOURS", "LANE_COLOUR", "VehicleMarker",
    "LaneLine", "SceneUpdate", "yaw_quaternion", "role_of_colour", "parse_vehicle_markers", "parse_road_markers",
    "vehicle_markers_cdr", "road_markers_cdr", "first_stamp_ns",
]

# -- what the markers mean (``scene/vehicles``, ``scene/road``) -----------------------------------
# visualization_msgs/Marker constants (the message's own values; spelled here so ROS-free code
# can build and read markers).
# visualization_msgs/Marker constants (the message's own values; spelled here so ROS-free code
# can build and read markers).
MARKER_CUBE, MARKER_LINE_STRIP = 1, 4


MARKER_ADD, MARKER_DELETE, MARKER_DELETEALL = 0, 2, 3


#: marker namespace of the vehicles on ``scene/vehicles`` and of the lanes on ``scene/road``
VEHICLE_NS, LANE_NS = "vehicles", "lanes"


#: height (z size) of a vehicle's cube, m; its centre sits at half this height
VEHICLE_HEIGHT = 1.5


#: the learning vehicle
EGO_ROLE = "ego"


#: a vehicle that is neither the ego nor in a neighbour slot
TRAFFIC_ROLE = "traffic"


#: the role of a vehicle in the scene: the ego, one of the observation's neighbour slots
#: (``sumo_bridge.observation.SLOT_NAMES``, in order), or other traffic
SCENE_ROLES: tuple[str, ...] = (EGO_ROLE, "leader", "follower", "left_leader", "left_follower", "right_leader",
                                "right_follower", TRAFFIC_ROLE)  # fmt: skip


#: RGBA of each role: the ego red, the slots of the current lane orange/yellow, of the left lane
#: greens, of the right lane blues (leaders darker than followers), traffic grey. A viewer tells
#: the roles apart by colour alone, and :func:`role_of_colour` reads a role back from a marker.
ROLE_COLOURS: dict[str, tuple[float, float, float, float]] = {
    EGO_ROLE: (0.85, 0.10, 0.10, 1.0),
    "leader": (1.0, 0.55, 0.0, 1.0),
    "follower": (0.95, 0.80, 0.15, 1.0),
    "left_leader": (0.05, 0.55, 0.20, 1.0),
    "left_follower": (0.45, 0.80, 0.40, 1.0),
    "right_leader": (0.10, 0.35, 0.85, 1.0),
    "right_follower": (0.45, 0.70, 1.0, 1.0),
    TRAFFIC_ROLE: (0.62, 0.62, 0.62, 1.0),
}


#: RGBA of the lanes on ``scene/road``
LANE_COLOUR = (0.30, 0.30, 0.33, 1.0)


_COLOUR_TOLERANCE = 2e-3  # ColorRGBA is float32


class VehicleMarker(NamedTuple):
    """One vehicle of ``scene/vehicles``: the cube's centre and heading in the map frame."""

    marker_id: int
    vehicle_id: str
    role: str
    x: float
    y: float
    #: heading, radians counter-clockwise from the map's x axis (REP 103)
    yaw: float
    length: float
    width: float


class LaneLine(NamedTuple):
    """One lane of ``scene/road``: its centre line (``(n, 2)`` float64, m) and width (m)."""

    lane_id: str
    points: np.ndarray
    width: float


class SceneUpdate(NamedTuple):
    """What one ``scene/vehicles`` message changes: vehicles added or moved, marker ids deleted, and
    whether everything known before was cleared first (a DELETEALL clears what came before it,
    markers being applied in array order as RViz applies them)."""

    stamp_ns: int
    vehicles: list[VehicleMarker]
    deleted: list[int]
    delete_all: bool


def yaw_quaternion(yaw: float) -> tuple[float, float]:
    """(z, w) of the quaternion of a rotation by ``yaw`` about the z axis (x = y = 0)."""
    return math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def role_of_colour(r: float, g: float, b: float) -> str:
    """The role whose colour (:data:`ROLE_COLOURS`) this is; ValueError naming the colour if none is."""
    for role, (cr, cg, cb, _a) in ROLE_COLOURS.items():
        if abs(r - cr) <= _COLOUR_TOLERANCE and abs(g - cg) <= _COLOUR_TOLERANCE and abs(b - cb) <= _COLOUR_TOLERANCE:
            return role
    raise ValueError(f"vehicle marker colour = ({r:.3f}, {g:.3f}, {b:.3f}), not the colour of any role in {SCENE_ROLES}")


def parse_vehicle_markers(msg: Any) -> SceneUpdate:
    """A ``scene/vehicles`` MarkerArray -> :class:`SceneUpdate` (markers of other namespaces are
    ignored, so a viewer may add its own); ValueError naming the marker and field if malformed."""
    vehicles: list[VehicleMarker] = []
    deleted: list[int] = []
    delete_all = False
    stamp = 0
    for i, m in enumerate(msg.markers):
        if i == 0:
            stamp = header_ns(m)
        if m.action == MARKER_DELETEALL:
            delete_all, vehicles, deleted = True, [], []
            continue
        if m.ns != VEHICLE_NS:
            continue
        if m.action == MARKER_DELETE:
            deleted.append(int(m.id))
            continue
        if m.action != MARKER_ADD:
            raise ValueError(f"scene/vehicles marker {i} (id {m.id}): action = {m.action}, expected "
                             f"ADD ({MARKER_ADD}), DELETE ({MARKER_DELETE}) or DELETEALL ({MARKER_DELETEALL})")
        if m.type != MARKER_CUBE:
            raise ValueError(f"scene/vehicles marker {i} (id {m.id}): type = {m.type}, expected CUBE ({MARKER_CUBE})")
        q = m.pose.orientation
        c = m.color
        vehicles.append(VehicleMarker(
            int(m.id), str(m.text), role_of_colour(c.r, c.g, c.b), float(m.pose.position.x), float(m.pose.position.y),
            2.0 * math.atan2(q.z, q.w), float(m.scale.x), float(m.scale.y),
        ))  # fmt: skip
    return SceneUpdate(stamp, vehicles, deleted, delete_all)


def parse_road_markers(msg: Any) -> list[LaneLine]:
    """The lanes of a ``scene/road`` MarkerArray (LINE_STRIPs of namespace ``lanes``), in message order."""
    lanes = []
    for i, m in enumerate(msg.markers):
        if m.ns != LANE_NS or m.action != MARKER_ADD:
            continue
        if m.type != MARKER_LINE_STRIP or len(m.points) < 2:
            raise ValueError(f"scene/road marker {i} ({m.text!r}): type {m.type} with {len(m.points)} points, "
                             f"expected a LINE_STRIP ({MARKER_LINE_STRIP}) of at least 2 points")
        pts = np.array([(p.x, p.y) for p in m.points], dtype=np.float64)
        lanes.append(LaneLine(str(m.text), pts, float(m.scale.x)))
    return lanes


# -- as CDR bytes ----------------------------------------------------------------------------------


_ID_TYPE_ACTION = struct.Struct("<iii").pack
_POSE_SCALE = struct.Struct("<10d").pack  # position xyz, orientation xyzw, scale xyz
_COLOUR_LIFETIME_LOCKED = struct.Struct("<4fiIB").pack  # color rgba, lifetime sec/nanosec, frame_locked
_POINT = struct.Struct("<3d").pack
_ZEROS = bytes(8)


_EMPTY = _string("")


class _Cdr:
    """A growing CDR buffer; ``align(n)`` pads to a multiple of n counted after the encapsulation."""

    __slots__ = ("buf",)

    def __init__(self, buf: bytearray | None = None) -> None:
        self.buf = bytearray(_ENCAPSULATION) if buf is None else buf

    def align(self, n: int) -> None:
        rem = (len(self.buf) - 4) % n
        if rem:
            self.buf += _ZEROS[: n - rem]

    def marker_head(self, stamp: tuple[int, int], frame: bytes, ns: bytes, marker_id: int, kind: int,
                    action: int) -> None:  # fmt: skip
        """header (stamp, frame_id), ns, id, type, action."""
        self.align(4)
        self.buf += _STAMP(*stamp)
        self.buf += frame
        self.buf += ns
        self.align(4)
        self.buf += _ID_TYPE_ACTION(marker_id, kind, action)

    def marker_tail(self, points: Sequence[tuple[float, float]], z: float, text: bytes) -> None:
        """points, colors (empty), texture_resource, texture, uv_coordinates, text, mesh_resource,
        mesh_file, mesh_use_embedded_materials: all empty or false but ``points`` and ``text``."""
        buf = self.buf
        self.align(4)
        buf += _U32(len(points))
        if points:
            self.align(8)
            for x, y in points:
                buf += _POINT(x, y, z)
        self.align(4)
        buf += _ZEROS[:4]  # colors: []
        buf += _EMPTY  # texture_resource
        self.align(4)
        buf += _ZEROS  # texture.header.stamp
        buf += _EMPTY  # texture.header.frame_id
        self.align(4)
        buf += _EMPTY  # texture.format
        self.align(4)
        buf += _ZEROS  # texture.data: [], uv_coordinates: []
        buf += text
        self.align(4)
        buf += _EMPTY  # mesh_resource
        self.align(4)
        buf += _EMPTY  # mesh_file.filename
        self.align(4)
        buf += _ZEROS[:4]  # mesh_file.data: []
        buf += b"\0"  # mesh_use_embedded_materials

    def pose_scale_colour(self, values: tuple[float, ...], colour: tuple[float, float, float, float]) -> None:
        self.align(8)
        self.buf += _POSE_SCALE(*values)
        self.buf += _COLOUR_LIFETIME_LOCKED(*colour, 0, 0, 0)


# The vehicles' CUBEs are the hot path (every vehicle, every step): the parts of a marker that do
# not change are laid out once, by their place in the record (the field order of _Cdr), so a marker
# costs two struct packs and a few appends. From a 4-aligned offset after the 25 bytes of colour,
# lifetime and frame_locked: 3 bytes of padding, then points [], colors [], texture_resource "",
# texture (stamp 0, frame_id "", format "", data []), uv_coordinates [] -- each string padded to 4.
_PRE_TEXT = b"\0" * 3 + bytes(8) + _EMPTY + bytes(3) + bytes(8) + _EMPTY + bytes(3) + _EMPTY + bytes(3) + bytes(8)
#: after ``text`` (padded to 4): mesh_resource "", mesh_file (filename "", data []), mesh_use_embedded_materials
_POST_TEXT = _EMPTY + bytes(3) + _EMPTY + bytes(3) + bytes(4) + b"\0"
_ROLE_TAIL = {role: _COLOUR_LIFETIME_LOCKED(*rgba, 0, 0, 0) + _PRE_TEXT for role, rgba in ROLE_COLOURS.items()}


def _stamp(stamp_ns: int) -> tuple[int, int]:
    return stamp_parts(stamp_ns, "marker stamp")


def vehicle_markers_cdr(vehicles: Iterable[VehicleMarker], removed: Sequence[int], stamp_ns: int,
                        frame_id: str = "map") -> bytes:  # fmt: skip
    """``scene/vehicles``: a CUBE per vehicle (centre at half its height, heading, length x width x
    :data:`~der_ros.contract.VEHICLE_HEIGHT`, its role's colour, ``text`` = its SUMO id), then a
    DELETE per marker id in ``removed``; every marker stamped ``stamp_ns`` in ``frame_id``."""
    vehicles = list(vehicles)
    head = _STAMP(*_stamp(stamp_ns)) + _string(frame_id) + _string(VEHICLE_NS)
    head += bytes(-len(head) % 4)  # header and ns, padded for the id that follows
    buf = bytearray(_ENCAPSULATION)
    buf += _U32(len(vehicles) + len(removed))
    z = 0.5 * VEHICLE_HEIGHT
    for v in vehicles:
        tail = _ROLE_TAIL.get(v.role)
        if tail is None:
            raise ValueError(f"vehicle {v.vehicle_id!r}: role = {v.role!r}, expected one of {tuple(ROLE_COLOURS)}")
        rem = (len(buf) - 4) & 3
        if rem:
            buf += _ZEROS[: 4 - rem]
        buf += head
        buf += _ID_TYPE_ACTION(v.marker_id, MARKER_CUBE, MARKER_ADD)
        if (len(buf) - 4) & 7:
            buf += _ZEROS[:4]
        half = 0.5 * v.yaw
        buf += _POSE_SCALE(v.x, v.y, z, 0.0, 0.0, math.sin(half), math.cos(half), v.length, v.width, VEHICLE_HEIGHT)
        buf += tail
        text = v.vehicle_id.encode()
        buf += _U32(len(text) + 1)
        buf += text
        buf += _ZEROS[: 1 + (-(len(text) + 1) % 4)]  # the NUL, then padding to 4
        buf += _POST_TEXT
    out = _Cdr(buf)
    stamp = _stamp(stamp_ns)
    frame, ns = _string(frame_id), _string(VEHICLE_NS)
    for marker_id in removed:
        out.marker_head(stamp, frame, ns, int(marker_id), MARKER_CUBE, MARKER_DELETE)
        out.pose_scale_colour((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))
        out.marker_tail((), 0.0, _EMPTY)
    return bytes(buf)


def road_markers_cdr(lanes: Sequence[LaneLine], stamp_ns: int = 0, frame_id: str = "map") -> bytes:
    """``scene/road``: a LINE_STRIP per lane along its centre line (z = 0), ``scale.x`` = the lane's
    width (RViz draws a ribbon that wide), :data:`~der_ros.contract.LANE_COLOUR`, ``text`` = the
    SUMO lane id; marker ids are the lanes' positions in ``lanes``."""
    stamp = _stamp(stamp_ns)
    frame, ns = _string(frame_id), _string(LANE_NS)
    out = _Cdr()
    out.buf += _U32(len(lanes))
    for i, lane in enumerate(lanes):
        out.marker_head(stamp, frame, ns, i, MARKER_LINE_STRIP, MARKER_ADD)
        out.pose_scale_colour((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, float(lane.width), 0.0, 0.0), LANE_COLOUR)
        points = [(float(x), float(y)) for x, y in lane.points]
        out.marker_tail(points, 0.0, _string(lane.lane_id))
    return bytes(out.buf)


def first_stamp_ns(data: bytes | memoryview) -> int | None:
    """The header stamp of the first marker of a CDR MarkerArray, read without decoding the rest
    (None for an empty array): lets a reader skip the vehicles of steps it does not draw."""
    if len(data) < 8 or bytes(data[:4]) != _ENCAPSULATION:
        raise ValueError(f"MarkerArray CDR: {len(data)} bytes starting {bytes(data[:4])!r}, expected little-endian "
                         "CDR (00 01 00 00) and a marker count")
    (count,) = struct.unpack_from("<I", data, 4)
    if count == 0:
        return None
    if len(data) < 16:
        raise ValueError(f"MarkerArray CDR: {count} markers in {len(data)} bytes, too short for a header stamp")
    sec, nanosec = struct.unpack_from("<iI", data, 8)
    return sec * _NS + nanosec
