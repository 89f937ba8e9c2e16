"""recorder_node as a real process: every message in order, finalised on SIGTERM, bounded loss on SIGKILL."""

from __future__ import annotations

import signal
import time
from pathlib import Path

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
