"""The per-step messages as CDR bytes (der_ros/contract/): rclpy decodes them into exactly the messages
built field by field in test/ros_messages.py, and rosbags' serialiser gives the same bytes."""

from __future__ import annotations

import numpy as np
import pytest
import ros_messages as ref
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2

from der_ros.bag.writer import jazzy_typestore
from der_ros.contract import (
    clock_cdr,
    cloud_to_points,
    command_cdr,
    ego_tf_cdr,
    header_ns,
    odometry_cdr,
    parse_command,
    parse_reward,
    read_command_cdr,
    read_odometry_pose_cdr,
    read_reward_cdr,
    read_state_cdr,
    reward_cdr,
    state_cdr,
    tf_cdr,
)
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import POINT_FIELDS

TS = jazzy_typestore()


def _check(data: bytes, expected: object, rclpy_type: type, rosbags_type: str) -> None:
    assert deserialize_message(data, rclpy_type) == expected
    assert bytes(TS.serialize_cdr(TS.deserialize_cdr(data, rosbags_type), rosbags_type)) == data


@pytest.mark.parametrize("rows", [1, 7])
@pytest.mark.parametrize("frame", ["ego", "", "é"])
def test_state(rows: int, frame: str) -> None:
    pts = np.random.default_rng(rows).normal(size=(rows, 12)) * 50.0
    stamp = 1_234_567_891_234
    _check(state_cdr(pts, stamp, frame, fields=POINT_FIELDS), ref.points_to_cloud(pts, stamp, frame), PointCloud2, "sensor_msgs/msg/PointCloud2")
    with pytest.raises(ValueError, match="shape"):
        state_cdr(pts[:, :5], stamp, fields=POINT_FIELDS)


@pytest.mark.parametrize("applied", [None, 0, 2, 17])
@pytest.mark.parametrize("flags", [(False, False), (True, False), (False, True)])
def test_reward(applied: int | None, flags: tuple[bool, bool]) -> None:
    for stamp, reward in ((0, 0.0), (5 * 10**8, -97.67), (10**12 + 1, 2.3388)):
        _check(reward_cdr(stamp, reward, *flags, applied), ref.make_reward(stamp, reward, *flags, applied),
               Vector3Stamped, "geometry_msgs/msg/Vector3Stamped")  # fmt: skip


def test_clock_and_odometry() -> None:
    for stamp in (0, 1, 3 * 10**9 + 7, 2**31 * 10**9 - 1):
        _check(clock_cdr(stamp), ref.make_clock(stamp), Clock, "rosgraph_msgs/msg/Clock")
    for frame, child in (("map", "ego"), ("world", ""), ("", "ego_vehicle")):
        for angle in (0.0, 33.0, 271.5):
            _check(odometry_cdr(10**9, 1.5, -2.0, angle, 9.5, frame, child),
                   ref.make_odometry(10**9, 1.5, -2.0, angle, 9.5, frame, child), Odometry, "nav_msgs/msg/Odometry")  # fmt: skip
    with pytest.raises(ValueError, match="expected >= 0"):
        clock_cdr(-1)


# -- reading them back without rclpy (der_ros/contract/): the fast path agrees with rclpy + the
# contract's parsers on every message, and says None (decode with rclpy) for any layout it does not own
def test_command() -> None:
    for stamp, action, sender in ((0, 0, ""), (123, 2, "/agent_node#12"), (10**12 + 5, 1, "/ns/agent_node#4567")):
        _check(command_cdr(stamp, action, sender), ref.make_command(stamp, action, sender), Joy, "sensor_msgs/msg/Joy")


def _flips(data: bytes, seed: int, n: int = 300) -> list[bytes]:
    """Copies of ``data`` with one random byte changed (a corrupted or foreign message)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        b = bytearray(data)
        b[int(rng.integers(len(b)))] = int(rng.integers(256))
        out.append(bytes(b))
    return out


def _rclpy_or_error(fn: object) -> object:
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - what the general path does with the bytes
        return type(exc)


@pytest.mark.parametrize("frame", ["ego", "", "é"])
def test_read_state(frame: str) -> None:
    pts = np.random.default_rng(3).normal(size=(9, 12)) * 50.0
    data = state_cdr(pts, 1_234_567_891_234, frame, fields=POINT_FIELDS)
    stamp, read = read_state_cdr(data, POINT_FIELDS)
    assert stamp == 1_234_567_891_234 and np.array_equal(read, pts) and read.flags.writeable
    assert read_state_cdr(state_cdr(pts[:0], 7, frame, fields=POINT_FIELDS), POINT_FIELDS)[1].shape == (0, 12)
    # rclpy's serialiser leaves padding bytes as they were: not our layout, so the general path decodes it
    general = serialize_message(ref.points_to_cloud(pts, 5, frame))
    fast = read_state_cdr(general, POINT_FIELDS)
    assert fast is None or (fast[0] == 5 and np.array_equal(fast[1], pts))
    # other layouts: None (another field table, big-endian encapsulation, truncated, trailing bytes)
    assert read_state_cdr(data, tuple(reversed(POINT_FIELDS))) is None
    assert read_state_cdr(b"\x01\x00" + data[2:], POINT_FIELDS) is None
    assert all(read_state_cdr(data[:n], POINT_FIELDS) is None for n in range(len(data)))
    assert read_state_cdr(data + bytes(4), POINT_FIELDS) is None
    # a value out of range: the same error as the contract's parser
    bad = pts.copy()
    bad[4, 6] = np.inf
    with pytest.raises(ValueError, match="state point 4 field") as fast_err:
        read_state_cdr(state_cdr(bad, 5, frame, fields=POINT_FIELDS), POINT_FIELDS)
    with pytest.raises(ValueError) as general_err:
        cloud_to_points(ref.points_to_cloud(bad, 5, frame), POINT_FIELDS)
    assert str(fast_err.value) == str(general_err.value)
    # corrupted bytes: whatever the fast path accepts, rclpy + cloud_to_points give the same
    for b in _flips(data, 11):
        try:
            fast = read_state_cdr(b, POINT_FIELDS)
        except ValueError as exc:
            with pytest.raises(ValueError, match=str(exc).split(" = ")[0]):
                cloud_to_points(deserialize_message(b, PointCloud2), POINT_FIELDS)
            continue
        if fast is not None:
            msg = deserialize_message(b, PointCloud2)
            assert fast[0] == header_ns(msg) and np.array_equal(fast[1], cloud_to_points(msg, POINT_FIELDS))


@pytest.mark.parametrize("applied", [None, 0, 2])
def test_read_reward(applied: int | None) -> None:
    for stamp, reward, flags in ((0, 0.0, (False, False)), (5 * 10**8, -97.67, (True, False)), (10**12 + 1, 2.3, (False, True))):
        for data in (reward_cdr(stamp, reward, *flags, applied),
                     serialize_message(ref.make_reward(stamp, reward, *flags, applied))):
            assert read_reward_cdr(data) == parse_reward(deserialize_message(data, Vector3Stamped))
    data = reward_cdr(5, 1.0, False, False, applied)
    assert read_reward_cdr(b"\x00\x00" + data[2:]) is None  # big-endian
    assert all(read_reward_cdr(data[:n]) is None for n in range(len(data)))
    for bad, what in ((float("nan"), "reward x"), (1e300, "reward x")):
        with pytest.raises(ValueError, match=what):
            read_reward_cdr(reward_cdr(5, bad, False, False, applied))
    for b in _flips(data, 12):
        fast = _rclpy_or_error(lambda b=b: read_reward_cdr(b))
        if fast is not None:
            assert fast == _rclpy_or_error(lambda b=b: parse_reward(deserialize_message(b, Vector3Stamped)))


def test_read_command() -> None:
    msgs = [ref.make_command(123, 2, "/agent_node#12"), Joy(buttons=[1, 0, 1], axes=[0.5, -1.0])]
    for msg in msgs:
        for data in (serialize_message(msg),):
            assert read_command_cdr(data) == parse_command(deserialize_message(data, Joy))
    data = command_cdr(10**12 + 5, 1, "/ns/agent_node#4567")
    assert read_command_cdr(data) == (10**12 + 5, [1], [], "/ns/agent_node#4567")
    assert read_command_cdr(b"\x00\x00" + data[2:]) is None  # big-endian: rclpy decodes it
    assert all(read_command_cdr(data[:n]) is None for n in range(len(data)))
    for b in _flips(serialize_message(msgs[1]), 13) + _flips(data, 14):
        fast = read_command_cdr(b)
        if fast is not None:  # nothing the fast path accepts is read differently by rclpy
            assert fast == _rclpy_or_error(lambda b=b: parse_command(deserialize_message(b, Joy)))


def test_the_nodes_rclpy_builders_are_the_contracts_bytes() -> None:
    """msg_conversions builds its messages from the contract's bytes: the same messages as the reference."""
    pts = np.random.default_rng(3).normal(size=(4, len(POINT_FIELDS)))
    assert mc.points_to_cloud(pts, 77, "ego") == ref.points_to_cloud(pts, 77, "ego")
    assert mc.make_reward(77, -1.5, True, False, 2) == ref.make_reward(77, -1.5, True, False, 2)
    assert mc.make_command(77, 1, "/agent") == ref.make_command(77, 1, "/agent")
    assert mc.make_odometry(77, 1.0, 2.0, 45.0, 9.0) == ref.make_odometry(77, 1.0, 2.0, 45.0, 9.0)
    assert mc.make_clock(77) == ref.make_clock(77)
    with pytest.raises(ValueError, match="expected >= 0"):
        mc.make_reward(-1, 0.0, False, False)


@pytest.mark.parametrize(("frame", "child"), [("map", "ego"), ("", "é"), ("world", "")])
def test_tf_and_the_odometry_pose_it_is_made_from(frame: str, child: str) -> None:
    """The recorder's ``/tf`` (issue 45): rosbags decodes the TFMessage to the odometry's pose and
    serialises it to the same bytes; the pose reader inverts ``odometry_cdr`` and refuses junk."""
    import math

    stamp = 987_654_321_123
    odom = odometry_cdr(stamp, 12.5, -3.0, 30.0, 9.0, frame, child)
    got = read_odometry_pose_cdr(odom)
    assert got is not None
    got_stamp, got_frame, got_child, pose = got
    yaw = math.radians(60.0)
    assert (got_stamp, got_frame, got_child) == (stamp, frame, child)
    assert pose == pytest.approx((12.5, -3.0, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
    tf = tf_cdr(got_stamp, pose[:3], pose[3:], got_frame, got_child)
    assert tf == ego_tf_cdr(stamp, 12.5, -3.0, 30.0, frame, child)
    msg = TS.deserialize_cdr(tf, "tf2_msgs/msg/TFMessage")
    (tr,) = msg.transforms
    assert (header_ns(tr), tr.header.frame_id, tr.child_frame_id) == (stamp, frame, child)
    t, r = tr.transform.translation, tr.transform.rotation
    assert (t.x, t.y, t.z, r.x, r.y, r.z, r.w) == pose
    assert bytes(TS.serialize_cdr(msg, "tf2_msgs/msg/TFMessage")) == tf
    for junk in (b"", odom[:30], b"\x00\x00\x00\x00" + odom[4:], odom[:70]):  # empty, cut, big-endian, cut in the pose
        assert read_odometry_pose_cdr(junk) is None
