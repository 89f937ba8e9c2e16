"""The bridge's step messages as ``rosbags`` objects, for tools that write bags without a bridge.

The rclpy builders the nodes publish with are :mod:`der_ros.nodes.msg_conversions`; these build
the same layouts (:mod:`der_ros.contract`) from the Jazzy typestore, so a bag written offline
(e.g. ``der graph``'s greedy episode, :mod:`der_ros.bag.episode_recording`) reads exactly like one
recorded from the graph. Episode events: :meth:`der_ros.bag.writer.BagWriter.mark_episode`; scene
markers: :mod:`der_ros.bag.scene_cdr` (CDR bytes).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from der_ros.bag.writer import jazzy_typestore
from der_ros.contract import POINTFIELD_FLOAT64, SAFETY_STATUS, applied_action_frame

__all__ = ["stamp", "clock_message", "reward_message", "state_message", "command_message"]

_NS = 1_000_000_000


def _types() -> dict[str, Any]:
    return jazzy_typestore().types


def stamp(ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of ``ns`` nanoseconds (>= 0)."""
    if ns < 0:
        raise ValueError(f"stamp = {ns} ns, expected >= 0")
    return _types()["builtin_interfaces/msg/Time"](sec=int(ns) // _NS, nanosec=int(ns) % _NS)


def _header(ns: int, frame_id: str) -> Any:
    return _types()["std_msgs/msg/Header"](stamp=stamp(ns), frame_id=frame_id)


def clock_message(ns: int) -> Any:
    """``/clock`` at ``ns``."""
    return _types()["rosgraph_msgs/msg/Clock"](clock=stamp(ns))


def reward_message(ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None) -> Any:
    """``reward``: x = reward, y/z = terminated/truncated, frame_id names the applied action."""
    t = _types()
    vec = t["geometry_msgs/msg/Vector3"](x=float(reward), y=1.0 if terminated else 0.0, z=1.0 if truncated else 0.0)
    return t["geometry_msgs/msg/Vector3Stamped"](header=_header(ns, applied_action_frame(applied_action)), vector=vec)


def state_message(ns: int, points: np.ndarray, fields: tuple[str, ...], frame_id: str = "ego") -> Any:
    """``state``: the points as an unordered PointCloud2 of FLOAT64 fields, little endian."""
    t = _types()
    pts = np.ascontiguousarray(points, dtype="<f8")
    if pts.ndim != 2 or pts.shape[1] != len(fields):
        raise ValueError(f"points have shape {pts.shape}, expected (n, {len(fields)}) for fields {fields}")
    pf = [t["sensor_msgs/msg/PointField"](name=n, offset=8 * i, datatype=POINTFIELD_FLOAT64, count=1)
          for i, n in enumerate(fields)]  # fmt: skip
    step = 8 * len(fields)
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(ns, frame_id), height=1, width=pts.shape[0], fields=pf, is_bigendian=False, point_step=step,
        row_step=step * pts.shape[0], data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=True,
    )  # fmt: skip


def command_message(ns: int, action: int, sender: str = "") -> Any:
    """``lane_change_cmd``: buttons[0] = action, stamped like the state it answers."""
    return _types()["sensor_msgs/msg/Joy"](header=_header(ns, sender), axes=np.zeros(0, dtype=np.float32),
                                           buttons=np.array([int(action)], dtype=np.int32))  # fmt: skip


def safety_message(ns: int, verdict: str, proposed: int, applied: int, interventions: int) -> Any:
    """``safety/interventions``: one record per command, as the safety node publishes it
    (:func:`der_ros.contract.parse_safety_record` reads it back)."""
    t = _types()
    values = [t["diagnostic_msgs/msg/KeyValue"](key=k, value=str(int(v)))
              for k, v in (("proposed", proposed), ("applied", applied), ("interventions", interventions))]  # fmt: skip
    status = t["diagnostic_msgs/msg/DiagnosticStatus"](level=1 if applied != proposed else 0, name=SAFETY_STATUS,
                                                      message=verdict, hardware_id="", values=values)  # fmt: skip
    return t["diagnostic_msgs/msg/DiagnosticArray"](header=_header(ns, ""), status=[status])
