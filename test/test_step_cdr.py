"""The bridge's per-step messages as CDR bytes (der_ros/bag/step_cdr.py): rclpy decodes them into exactly
the messages of the builders in der_ros/nodes/msg_conversions.py, and rosbags' serialiser gives the same bytes."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from der_ros.bag.step_cdr import clock_cdr, odometry_cdr, reward_cdr, state_cdr
from der_ros.bag.writer import jazzy_typestore
from der_ros.nodes import msg_conversions as mc

TS = jazzy_typestore()


def _check(data: bytes, expected: object, rclpy_type: type, rosbags_type: str) -> None:
    assert deserialize_message(data, rclpy_type) == expected
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(data, rosbags_type), rosbags_type)) == data


@pytest.mark.parametrize("rows", [1, 7])
@pytest.mark.parametrize("frame", ["ego", "", "é"])
def test_state(rows: int, frame: str) -> None:
    pts = np.random.default_rng(rows).normal(size=(rows, 12)) * 50.0
    stamp = 1_234_567_891_234
    _check(state_cdr(pts, stamp, frame), mc.points_to_cloud(pts, stamp, frame), PointCloud2, "sensor_msgs/msg/PointCloud2")
    with pytest.raises(ValueError, match="shape"):
        state_cdr(pts[:, :5], stamp)


@pytest.mark.parametrize("applied", [None, 0, 2, 17])
@pytest.mark.parametrize("flags", [(False, False), (True, False), (False, True)])
def test_reward(applied: int | None, flags: tuple[bool, bool]) -> None:
    for stamp, reward in ((0, 0.0), (5 * 10**8, -97.67), (10**12 + 1, 2.3388)):
        _check(reward_cdr(stamp, reward, *flags, applied), mc.make_reward(stamp, reward, *flags, applied),
               Vector3Stamped, "geometry_msgs/msg/Vector3Stamped")  # fmt: skip


def test_clock_and_odometry() -> None:
    for stamp in (0, 1, 3 * 10**9 + 7, 2**31 * 10**9 - 1):
        _check(clock_cdr(stamp), mc.make_clock(stamp), Clock, "rosgraph_msgs/msg/Clock")
    for frame, child in (("map", "ego"), ("world", ""), ("", "ego_vehicle")):
        for angle in (0.0, 33.0, 271.5):
            _check(odometry_cdr(10**9, 1.5, -2.0, angle, 9.5, frame, child),
                   mc.make_odometry(10**9, 1.5, -2.0, angle, 9.5, frame, child), Odometry, "nav_msgs/msg/Odometry")  # fmt: skip
    with pytest.raises(ValueError, match="expected >= 0"):
        clock_cdr(-1)
