"""Round trips of the pure message conversions (through CDR serialization, as on the wire)."""

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Joy, PointCloud2, PointField

from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import POINT_FIELDS, SLOT_NAMES, ObservationConfig, encode_observation


def wire(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def test_time_roundtrip_and_validation():
    for ns in (0, 1, 999_999_999, 1_000_000_000, 123 * 10**9 + 456, 2**40):
        t = mc.ns_to_time(ns)
        assert mc.time_to_ns(wire(mc.make_clock(ns)).clock) == ns == mc.time_to_ns(t)
        assert 0 <= t.nanosec < 10**9
    with pytest.raises(ValueError):
        mc.ns_to_time(-1)


def test_points_cloud_roundtrip_bit_identical_observation():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1 + len(SLOT_NAMES), len(POINT_FIELDS))) * 50
    msg = wire(mc.points_to_cloud(pts, 1_500_000_000))
    assert [f.name for f in msg.fields] == list(POINT_FIELDS)
    assert all(f.datatype == PointField.FLOAT64 for f in msg.fields)
    assert msg.width == pts.shape[0] and msg.height == 1 and msg.point_step == 8 * len(POINT_FIELDS)
    assert mc.time_to_ns(msg.header.stamp) == 1_500_000_000
    back = mc.cloud_to_points(msg)
    assert back.dtype == np.float64 and np.array_equal(back, pts)
    cfg = ObservationConfig()
    assert np.array_equal(encode_observation(back, cfg), encode_observation(pts, cfg))


def test_cloud_decoder_rejects_wrong_layouts():
    pts = np.zeros((7, len(POINT_FIELDS)))
    msg = mc.points_to_cloud(pts, 0)
    bad = PointCloud2()
    bad.fields = list(msg.fields)[:-1]
    with pytest.raises(ValueError, match="fields"):
        mc.cloud_to_points(bad)
    bad = mc.points_to_cloud(pts, 0)
    bad.fields[3].datatype = PointField.FLOAT32
    with pytest.raises(ValueError, match="speed"):
        mc.cloud_to_points(bad)
    bad = mc.points_to_cloud(pts, 0)
    bad.data = bytes(len(bad.data) - 8)
    with pytest.raises(ValueError, match="bytes"):
        mc.cloud_to_points(bad)
    with pytest.raises(ValueError, match="shape"):
        mc.points_to_cloud(np.zeros((7, 3)), 0)


def test_big_endian_cloud_decodes():
    pts = np.arange(7 * len(POINT_FIELDS), dtype=np.float64).reshape(7, -1)
    msg = mc.points_to_cloud(pts, 0)
    msg.is_bigendian = True
    msg.data = pts.astype(">f8").tobytes()
    assert np.array_equal(mc.cloud_to_points(msg), pts)


@pytest.mark.parametrize("angle", [0.0, 45.0, 90.0, 180.0, 271.5])
def test_odometry_roundtrip(angle):
    msg = wire(mc.make_odometry(42, 10.5, -3.0, angle, 12.25))
    stamp, x, y, a, v = mc.odometry_pose(msg)
    assert (stamp, x, y, v) == (42, 10.5, -3.0, 12.25)
    assert a == pytest.approx(angle, abs=1e-9)
    assert isinstance(msg, Odometry) and msg.header.frame_id == "map" and msg.child_frame_id == "ego"
    q = msg.pose.pose.orientation
    assert q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2 == pytest.approx(1.0)


def test_odometry_heading_convention():
    # SUMO angle 90 = heading east = ROS yaw 0; SUMO 0 = north = yaw +90 deg
    q = mc.make_odometry(0, 0, 0, 90.0, 0).pose.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.0)
    q = mc.make_odometry(0, 0, 0, 0.0, 0).pose.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(math.pi / 2)


def test_reward_roundtrip_and_validation():
    for r, te, tr in ((0.0, False, False), (-1.5, True, False), (2.0, False, True)):
        assert mc.parse_reward(wire(mc.make_reward(7, r, te, tr))) == (7, r, te, tr)
    m = mc.make_reward(0, 0.0, False, False)
    m.vector.x = math.nan
    with pytest.raises(ValueError, match="finite"):
        mc.parse_reward(m)
    m = mc.make_reward(0, 0.0, False, False)
    m.vector.y = 0.5
    with pytest.raises(ValueError, match="terminated"):
        mc.parse_reward(m)
    assert isinstance(m, Vector3Stamped)


def test_applied_action_in_reward_frame_id():
    assert mc.parse_applied_action(wire(mc.make_reward(0, 0.0, False, False))) is None
    msg = wire(mc.make_reward(5, 1.0, False, False, applied_action=2))
    assert mc.parse_applied_action(msg) == 2 and mc.parse_reward(msg) == (5, 1.0, False, False)
    msg.header.frame_id = mc.APPLIED_ACTION_PREFIX + "x"
    with pytest.raises(ValueError, match="applied_action"):
        mc.parse_applied_action(msg)


def test_command_roundtrip():
    msg = wire(mc.make_command(3 * 10**8, 2, sender="agent#1"))
    assert isinstance(msg, Joy)
    assert mc.parse_command(msg) == (3 * 10**8, [2], [], "agent#1")


def test_episode_event_roundtrip():
    values = {"episode": 3, "steps": 120, "return": -4.25, "lane_changes": 2, "mean_speed": 9.5}
    msg = wire(mc.make_episode_event(5 * 10**9, "collision", values))
    assert isinstance(msg, DiagnosticArray)
    ((stamp, event, got),) = mc.parse_episode_events(msg)
    assert (stamp, event, got) == (5 * 10**9, "collision", values)
    assert msg.status[0].level == DiagnosticStatus.WARN
    assert mc.parse_episode_events(wire(mc.metrics_to_diagnostics({"a": 1.0}, 0))) == []


def test_metrics_roundtrip_exact():
    metrics = {"charts/episodic_return": -12.5, "losses/td_loss": 1 / 3, "replay/h2_size": 17.0}
    msg = wire(mc.metrics_to_diagnostics(metrics, 10, hardware_id="agent_node"))
    assert mc.diagnostics_to_metrics(msg) == metrics  # repr keeps every float bit
    assert mc.diagnostics_to_metrics(msg, names=["other"]) == {}
