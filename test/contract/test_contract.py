"""The graph contract: the topic table, and round trips builder (rclpy) -> CDR -> contract parser.

Every parser of :mod:`der_ros.contract` is checked on the rclpy message (as a node receives it)
and on the same CDR bytes decoded by rosbags (as the offline tools read a bag): both must give
the same result, bit for bit.
"""

import math
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Joy, PointCloud2, PointField

from der_ros import contract as ct
from der_ros.bag.writer import jazzy_typestore
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import POINT_FIELDS, SLOT_NAMES, ObservationConfig, encode_observation

TS = jazzy_typestore()
GRAPH_DOC = Path(__file__).resolve().parents[2] / "docs" / "graph.md"


def wire(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def from_bag(msg):
    """The same message as the offline tools see it: CDR bytes decoded by rosbags."""
    t = type(msg)
    msgtype = f"{t.__module__.split('.')[0]}/msg/{t.__name__}"
    return TS.deserialize_cdr(serialize_message(msg), msgtype)


def both(msg):
    """The message as a node receives it and as a bag reader decodes it."""
    return wire(msg), from_bag(msg)


def test_time_roundtrip_and_validation():
    for ns in (0, 1, 999_999_999, 1_000_000_000, 123 * 10**9 + 456, 2**40):
        t = mc.ns_to_time(ns)
        assert ct.stamp_to_ns(wire(mc.make_clock(ns)).clock) == ns == ct.stamp_to_ns(t)
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
    assert ct.stamp_to_ns(msg.header.stamp) == 1_500_000_000
    back = ct.cloud_to_points(msg)
    assert back.dtype == np.float64 and np.array_equal(back, pts)
    bag = from_bag(mc.points_to_cloud(pts, 1_500_000_000))  # rosbags: data is a uint8 ndarray
    assert np.array_equal(ct.cloud_to_points(bag, POINT_FIELDS), pts)
    assert ct.point_field_names(bag) == POINT_FIELDS
    cfg = ObservationConfig()
    assert np.array_equal(encode_observation(back, cfg), encode_observation(pts, cfg))


def test_cloud_decoder_rejects_wrong_layouts():
    pts = np.zeros((7, len(POINT_FIELDS)))
    msg = mc.points_to_cloud(pts, 0)
    bad = PointCloud2()
    bad.fields = list(msg.fields)[:-1]
    with pytest.raises(ValueError, match="fields"):
        ct.cloud_to_points(bad, POINT_FIELDS)
    bad = mc.points_to_cloud(pts, 0)
    bad.fields[3].datatype = PointField.FLOAT32
    with pytest.raises(ValueError, match="speed"):
        ct.cloud_to_points(bad, POINT_FIELDS)
    bad = mc.points_to_cloud(pts, 0)
    bad.data = bytes(len(bad.data) - 8)
    with pytest.raises(ValueError, match="bytes"):
        ct.cloud_to_points(bad, POINT_FIELDS)
    with pytest.raises(ValueError, match="shape"):
        mc.points_to_cloud(np.zeros((7, 3)), 0)


def test_big_endian_cloud_decodes():
    pts = np.arange(7 * len(POINT_FIELDS), dtype=np.float64).reshape(7, -1)
    msg = mc.points_to_cloud(pts, 0)
    msg.is_bigendian = True
    msg.data = pts.astype(">f8").tobytes()
    assert np.array_equal(ct.cloud_to_points(msg), pts)


@pytest.mark.parametrize("angle", [0.0, 45.0, 90.0, 180.0, 271.5])
def test_odometry_roundtrip(angle):
    msg = wire(mc.make_odometry(42, 10.5, -3.0, angle, 12.25))
    stamp, x, y, a, v = ct.odometry_pose(msg)
    assert (stamp, x, y, v) == (42, 10.5, -3.0, 12.25)
    assert a == pytest.approx(angle, abs=1e-9)
    assert ct.odometry_pose(from_bag(mc.make_odometry(42, 10.5, -3.0, angle, 12.25))) == (stamp, x, y, a, v)
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
        for m in both(mc.make_reward(7, r, te, tr)):
            assert ct.parse_reward(m) == (7, r, te, tr, None)
    m = mc.make_reward(0, 0.0, False, False)
    m.vector.x = math.nan
    with pytest.raises(ValueError, match="finite"):
        ct.parse_reward(m)
    m = mc.make_reward(0, 0.0, False, False)
    m.vector.y = 0.5
    with pytest.raises(ValueError, match="terminated"):
        ct.parse_reward(m)
    assert isinstance(m, Vector3Stamped)


def test_applied_action_in_reward_frame_id():
    for msg in both(mc.make_reward(0, 0.0, False, False)):
        assert ct.parse_applied_action(msg) is None
    for msg in both(mc.make_reward(5, 1.0, False, False, applied_action=2)):
        assert ct.parse_applied_action(msg) == 2 and ct.parse_reward(msg) == (5, 1.0, False, False, 2)
    msg = wire(mc.make_reward(5, 1.0, False, False, applied_action=2))
    msg.header.frame_id = ct.APPLIED_ACTION_PREFIX + "x"
    with pytest.raises(ValueError, match="applied_action"):
        ct.parse_applied_action(msg)


@pytest.mark.parametrize("digits", ["\u0661", "\u0967", "\uff11", " 1", "+1", "1_0", "-1", "1 ", "", "1" * 10])
def test_an_applied_action_in_other_digits_or_spellings_is_refused(digits):
    """int() reads the Arabic-Indic one (and ' 1', '+1', '1_0') as 1: the agent would store a wrong action."""
    with pytest.raises(ValueError, match="ASCII digits"):
        ct.reward_from_fields(5, ct.APPLIED_ACTION_PREFIX + digits, 1.0, 0.0, 0.0)
    assert ct.reward_from_fields(5, ct.APPLIED_ACTION_PREFIX + "1", 1.0, 0.0, 0.0).applied_action == 1


def test_command_roundtrip():
    live, bag = both(mc.make_command(3 * 10**8, 2, sender="agent#1"))
    assert isinstance(live, Joy)
    for msg in (live, bag):
        assert ct.parse_command(msg) == (3 * 10**8, [2], [], "agent#1")
        assert ct.command_action(msg) == 2
    live.buttons = []
    with pytest.raises(ValueError, match="buttons"):
        ct.command_action(live)


def test_episode_event_roundtrip():
    values = {"episode": 3, "steps": 120, "return": -4.25, "lane_changes": 2, "mean_speed": 9.5}
    live, bag = both(mc.make_episode_event(5 * 10**9, "collision", values))
    assert isinstance(live, DiagnosticArray)
    for msg in (live, bag):
        ((stamp, event, got),) = ct.parse_episode_events(msg)
        assert (stamp, event, got) == (5 * 10**9, "collision", values)
    assert live.status[0].level == DiagnosticStatus.WARN
    assert ct.parse_episode_events(wire(mc.metrics_to_diagnostics({"a": 1.0}, 0))) == []


def test_metrics_roundtrip_exact():
    metrics = {"charts/episodic_return": -12.5, "losses/td_loss": 1 / 3, "replay/h2_size": 17.0}
    for msg in both(mc.metrics_to_diagnostics(metrics, 10, hardware_id="agent_node")):
        assert ct.diagnostics_to_metrics(msg) == metrics  # repr keeps every float bit
        assert ct.diagnostics_to_metrics(msg, names=["other"]) == {}
        assert ct.diagnostics_to_metrics(msg, names=[ct.METRICS_STATUS]) == metrics


def test_topic_table() -> None:
    names = [t.name for t in ct.TOPICS]
    assert [t.name for t in ct.TOPICS if t.record] == ct.default_record_topics()
    assert ct.BRIDGE_DIAGNOSTICS in names and ct.BRIDGE_DIAGNOSTICS in ct.default_record_topics()  # issue 45: recorded
    assert {"/clock", "state", "reward", "episode", "lane_change_cmd", "agent/metrics", "ego/odom"} <= set(names)
    for t in ct.TOPICS:
        assert t.msgtype in TS.fielddefs, t.msgtype
        assert ct.topic_spec(t.name) is t
    assert ct.topic_by_name("/robot1/agent/metrics").name == "agent/metrics"
    assert ct.topic_by_name("/episode").name == "episode"
    assert ct.topic_by_name("/other") is None
    md = ct.topics_markdown()
    rows = [ln for ln in md.splitlines() if ln.startswith("| `")]
    assert len(rows) == len(ct.TOPICS)
    assert "| `state` | sensor_msgs/PointCloud2 |" in md and "RELIABLE, KEEP_LAST 50" in md
    assert "BEST_EFFORT, KEEP_LAST 5" in md  # ego/odom: sensor data
    spec = ct.QosSpec(reliability="best_effort", depth=3)
    assert ct.QosSpec.from_rosbag2(spec.to_rosbag2()) == spec
    with pytest.raises(ValueError, match="reliability"):
        ct.QosSpec(reliability="sometimes")


def test_rclpy_profiles_are_the_table() -> None:
    """The one conversion to rclpy keeps reliability, durability and depth of every topic."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy, qos_profile_sensor_data

    from der_ros.contract_ros import qos_to_rosbag2, topic_qos

    for t in ct.TOPICS:
        q = topic_qos(t.name)
        assert q.depth == t.qos.depth
        assert (q.reliability == ReliabilityPolicy.BEST_EFFORT) == t.qos.best_effort
        assert (q.durability == DurabilityPolicy.TRANSIENT_LOCAL) == t.qos.transient_local
        assert q.durability in (DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL)
        assert ct.QosSpec.from_rosbag2(qos_to_rosbag2(q)) == t.qos  # and back, as the recorder writes it
    sensor = topic_qos(ct.ODOM)
    assert (sensor.reliability, sensor.depth, sensor.history) == (
        qos_profile_sensor_data.reliability, qos_profile_sensor_data.depth, qos_profile_sensor_data.history)


def test_recorded_qos_spellings() -> None:
    """rosbag2 metadata before version 9 wrote integer enums; both spellings parse the same."""
    names = ct.parse_qos_profiles("- {reliability: best_effort, durability: volatile, history: keep_last, depth: 5}")
    ints = ct.parse_qos_profiles("- {reliability: 2, durability: 2, history: 1, depth: 5}")
    assert names == ints
    assert ct.merged_qos(names) == ct.SENSOR_DATA
    assert ct.qos_text(names) == "BEST_EFFORT, KEEP_LAST 5"
    assert ct.parse_qos_profiles("not: [valid") == () and ct.parse_qos_profiles(None) == ()


def test_graph_doc_topic_table_is_the_rendered_table() -> None:
    """docs/graph.md's topic table is ``topics_markdown()`` verbatim (regenerate it when TOPICS changes)."""
    assert ct.topics_markdown() in GRAPH_DOC.read_text()
