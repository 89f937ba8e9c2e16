"""recorder_node as a real process: every message in order, finalised on SIGTERM, bounded loss on SIGKILL."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import yaml
from mcap.records import Message
from mcap.stream_reader import StreamReader
from ros_harness import *  # noqa: F403 - fixtures ros_graph / ros_domain
from ros_harness import wait_for
from rosbags.interfaces import QosReliability
from rosbags.rosbag2 import Reader

from der_ros.bag.writer import FINALIZED_KEY, jazzy_typestore, read_episode_summary

TS = jazzy_typestore()
MODULE = "der_ros.nodes.recorder_node"


def metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def publish_when_matched(graph, pub, proc, what: str) -> None:  # noqa: ANN001
    wait_for(lambda: pub.get_subscription_count() >= 1, 30, what=f"recorder subscribed to {what}", procs=[proc])


def test_records_every_message_in_order_and_finalises_on_sigterm(ros_graph, tmp_path: Path) -> None:
    from sensor_msgs.msg import Joy
    from std_msgs.msg import String

    from der_ros.nodes.msg_conversions import make_episode_event

    bag = tmp_path / "bag"
    rec = ros_graph.start_node(
        MODULE,
        params={
            "output": str(bag),
            "topics": ["lane_change_cmd", "episode", "extra/chatter"],
            "all_topics": True,
            "discovery_period": 0.2,
            "flush_every_messages": 25,
        },
    )
    probe = ros_graph.probe
    cmd = probe.publisher("lane_change_cmd", Joy, 10)
    chatter = probe.publisher("extra/chatter", String, 10)
    other = probe.publisher("not_listed", String, 10)  # only recorded because all_topics is true
    from diagnostic_msgs.msg import DiagnosticArray
    episode = probe.publisher("episode", DiagnosticArray, 100)
    for pub, name in ((cmd, "lane_change_cmd"), (chatter, "extra/chatter"), (other, "not_listed"), (episode, "episode")):
        publish_when_matched(ros_graph, pub, rec, name)

    n = 300
    episode.publish(make_episode_event(1_000, "start", {"episode": 0, "steps": 0, "return": 0.0}))
    for i in range(n):
        m = Joy()
        m.header.stamp.sec = i
        m.buttons = [i % 3]
        cmd.publish(m)
        if i % 10 == 0:
            chatter.publish(String(data=f"c{i}"))
            other.publish(String(data=f"o{i}"))
        if i % 50 == 0:
            time.sleep(0.01)  # let a reliable writer's history (depth 10) drain
    episode.publish(make_episode_event(2_000, "collision", {"episode": 0, "steps": n, "return": -2.5}))

    # wait until the flushes show everything on disk, then stop the recorder with SIGTERM
    wait_for(lambda: metadata(bag)["message_count"] >= n + 2 * (n // 10) + 2, 30, what="all messages flushed",
             procs=[rec])
    rec.signal(signal.SIGTERM)
    assert rec.wait(timeout=20) == 0, rec.output()[-3000:]
    assert "bag closed" in rec.output()

    meta = metadata(bag)
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts["/lane_change_cmd"] == n
    assert counts["/extra/chatter"] == n // 10 and counts["/not_listed"] == n // 10
    assert counts["/episode"] == 2
    assert "/rosout" not in counts and "/parameter_events" not in counts  # excluded by default
    assert meta["message_count"] == sum(counts.values())
    episodes = read_episode_summary(bag)
    assert [(e["event"], e["episode"]) for e in episodes] == [("start", 0), ("collision", 0)]
    assert episodes[1]["return"] == -2.5 and episodes[1]["stamp_ns"] == 2_000

    with Reader(bag) as r:
        conns = {c.topic: c for c in r.connections}
        qos = conns["/lane_change_cmd"].ext.offered_qos_profiles
        assert qos and qos[0].reliability == QosReliability.RELIABLE  # the publisher's, from graph introspection
        stamps, last_t = [], 0
        for c, t, data in r.messages(connections=[conns["/lane_change_cmd"]]):
            msg = TS.deserialize_cdr(data, c.msgtype)
            stamps.append(msg.header.stamp.sec)
            assert int(msg.buttons[0]) == msg.header.stamp.sec % 3
            assert t >= last_t
            last_t = t
        assert stamps == list(range(n))  # every message, in publication order
        texts = [TS.deserialize_cdr(d, c.msgtype).data for c, _, d in r.messages(connections=[conns["/extra/chatter"]])]
        assert texts == [f"c{i}" for i in range(0, n, 10)]
        # log_time is receive time on the recorder's (system) clock
        first_t = next(t for _, t, _ in r.messages())
        assert abs(first_t - time.time_ns()) < 120e9


def test_sigkill_leaves_a_bag_readable_up_to_the_last_flush(ros_graph, tmp_path: Path) -> None:
    from std_msgs.msg import String

    bag = tmp_path / "killed"
    rec = ros_graph.start_node(
        MODULE,
        params={"output": str(bag), "topics": ["chatter"], "flush_every_messages": 100000,
                "flush_every_seconds": 0.3, "discovery_period": 0.1},
    )
    pub = ros_graph.probe.publisher("chatter", String, 10)
    publish_when_matched(ros_graph, pub, rec, "chatter")
    first = 120
    for i in range(first):
        pub.publish(String(data=str(i)))
        if i % 10 == 9:
            time.sleep(0.005)
    # the timer-driven flush puts them on disk within flush_every_seconds
    wait_for(lambda: metadata(bag)["message_count"] == first, 10, what="time-based flush", procs=[rec])
    extra = 7
    for i in range(first, first + extra):
        pub.publish(String(data=str(i)))
    rec.signal(signal.SIGKILL)
    rec.wait(timeout=10)

    meta = metadata(bag)
    assert meta["custom_data"][FINALIZED_KEY] == "false"
    streamed: list[Message] = []
    with open(bag / "killed_0.mcap", "rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Message):
                    streamed.append(record)
        except Exception:  # the file ends without a footer
            pass
    texts = [TS.deserialize_cdr(m.data, "std_msgs/msg/String").data for m in streamed]
    # everything flushed is there, in order; at most the unflushed tail (the 7 sent last) is lost
    assert first <= len(texts) <= first + extra
    assert texts == [str(i) for i in range(len(texts))]
    assert meta["message_count"] <= len(texts)


def test_bad_parameter_is_rejected_at_start(ros_graph, tmp_path: Path) -> None:
    rec = ros_graph.start_node(MODULE, params={"output": str(tmp_path / "b"), "compression": "bz2"})
    assert rec.wait(timeout=30) != 0
    assert "compression" in rec.output() and "bz2" in rec.output()
    assert not (tmp_path / "b").exists()


def test_scene_topics_are_recorded_by_default_and_the_road_though_published_before_matching(
        ros_graph, tmp_path: Path) -> None:  # fmt: skip
    """The default topics include the scene markers. scene/road is published once, as the bridge does, at
    once after its publisher is created, before the recorders (already subscribed by name) have matched it:
    only a transient-local subscription (the table's QoS) still gets it. With record_scene false neither
    marker topic is recorded."""
    from visualization_msgs.msg import MarkerArray

    from der_ros import contract as ct
    from der_ros.contract import road_markers_cdr, vehicle_markers_cdr
    from der_ros.contract_ros import topic_qos
    from der_ros.nodes.msg_conversions import make_episode_event

    probe = ros_graph.probe
    with_scene = ros_graph.start_node(MODULE, params={"output": str(tmp_path / "scene"), "discovery_period": 0.2})
    without = ros_graph.start_node(MODULE, params={"output": str(tmp_path / "plain"), "discovery_period": 0.2,
                                                   "record_scene": False})  # fmt: skip
    lane = ct.LaneLine("e_0", np.array([[0.0, 0.0], [10.0, 0.0]]), 3.2)
    road = probe.publisher(ct.SCENE_ROAD, MarkerArray, topic_qos(ct.SCENE_ROAD))
    road.publish(road_markers_cdr([lane]))  # no wait for a match
    vehicles = probe.publisher(ct.SCENE_VEHICLES, MarkerArray, topic_qos(ct.SCENE_VEHICLES))
    from diagnostic_msgs.msg import DiagnosticArray

    episode = probe.publisher(ct.EPISODE, DiagnosticArray, 100)
    publish_when_matched(ros_graph, vehicles, with_scene, ct.SCENE_VEHICLES)
    wait_for(lambda: episode.get_subscription_count() >= 2, 30, what="both recorders on episode",
             procs=[with_scene, without])  # fmt: skip
    marker = ct.VehicleMarker(0, "ego", "ego", 1.0, 2.0, 0.5, 5.0, 1.8)
    for k in range(5):
        vehicles.publish(vehicle_markers_cdr([marker._replace(x=float(k))], [], k * 500_000_000))
    episode.publish(make_episode_event(0, "start", {"episode": 0, "steps": 0}))
    for rec, bag, expected in ((with_scene, tmp_path / "scene", 7), (without, tmp_path / "plain", 1)):
        wait_for(lambda bag=bag, expected=expected: metadata(bag)["message_count"] >= expected, 30,
                 what=f"messages in {bag.name}", procs=[rec])  # fmt: skip
        rec.signal(signal.SIGTERM)
        assert rec.wait(timeout=20) == 0, rec.output()[-3000:]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in metadata(tmp_path / "scene")["topics_with_message_count"]}
    assert counts["/scene/road"] == 1 and counts["/scene/vehicles"] == 5 and counts["/episode"] == 1
    plain = {t["topic_metadata"]["name"]: t["message_count"] for t in metadata(tmp_path / "plain")["topics_with_message_count"]}
    assert plain == {"/episode": 1}
    with Reader(tmp_path / "scene") as r:
        (conn,) = [c for c in r.connections if c.topic == "/scene/road"]
        (lanes,) = [ct.parse_road_markers(TS.deserialize_cdr(d, conn.msgtype)) for _, _, d in r.messages([conn])]
    assert [x.lane_id for x in lanes] == ["e_0"] and np.array_equal(lanes[0].points, lane.points)
