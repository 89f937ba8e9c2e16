"""``der bag play``: every message republished, per-topic order kept, recorded timing within tolerance.

The ROS test runs the player as a separate process (``python -m der_ros.cli replay play``) in
the test's own ROS_DOMAIN_ID with LOCALHOST discovery and receives with raw (CDR bytes)
subscriptions in an in-process rclpy node (test/ros_harness.py).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from bag_helpers import record_env_bag, write_foreign_bag, write_json_mcap, write_mistyped_bag
from ros_harness import NodeProcess, ros_domain, ros_graph, wait_for  # noqa: F401 (fixtures)

from der_ros.bag.reader import BagReader
from der_ros.contract import QosSpec, merged_qos
from der_ros.offline.play import play_bag


class _SimClock:
    """The player's clock in these tests: ``sleep`` advances it exactly (no wall-clock thresholds in
    tests; the real player's timing is measured in bench/)."""

    def __init__(self) -> None:
        self.t = 1000.0
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds


def _expected(bag: Path, topics: set[str] | None = None) -> list[tuple[str, int, bytes]]:
    return [(m.topic, m.log_time, bytes(m.data)) for m in BagReader(bag).messages(topics)]


class _FakePub:
    def __init__(self, topic: str, out: list[tuple[float, str, bytes]], qos: Any, clock: _SimClock) -> None:
        self.topic_name = topic
        self.out = out
        self.qos = qos
        self.clock = clock

    def publish(self, data: Any) -> None:
        self.out.append((self.clock.now(), self.topic_name, data))

    def get_subscription_count(self) -> int:
        return 1


class _FakeNode:
    def __init__(self) -> None:
        self.out: list[tuple[float, str, bytes]] = []
        self.pubs: dict[str, _FakePub] = {}
        self.clock = _SimClock()

    def create_publisher(self, cls: type, topic: str, qos: Any) -> _FakePub:
        self.pubs[topic] = _FakePub(topic, self.out, qos, self.clock)
        return self.pubs[topic]

    def play(self, reader: BagReader, **kw: Any) -> int:
        return play_bag(self, reader, now=self.clock.now, sleep=self.clock.sleep, **kw)


def test_play_schedule_filter_and_qos_without_dds(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    record_env_bag(bag, episodes=1, max_episode_steps=6)
    node = _FakeNode()
    n = node.play(BagReader(bag), rate=10.0, topics=["/state", "/reward"])
    want = _expected(bag, {"/state", "/reward"})
    assert n == len(want)
    assert [(t, d) for _, t, d in node.out] == [(t, d) for t, _, d in want]
    t0, l0 = node.out[0][0], want[0][1]
    assert [tp - t0 for tp, _, _ in node.out] == pytest.approx([(lt - l0) / 1e9 / 10.0 for _, lt, _ in want],
                                                               abs=1e-9)  # the recorded gaps, scaled by the rate
    assert all(s > 0 for s in node.clock.sleeps) and len(node.clock.sleeps) < n  # no sleep within one stamp
    from rclpy.qos import ReliabilityPolicy

    assert node.pubs["/state"].qos.depth == 50
    assert node.pubs["/state"].qos.reliability == ReliabilityPolicy.RELIABLE
    assert merged_qos(({"reliability": "reliable", "depth": 5}, {"reliability": "best_effort", "depth": 7})) == QosSpec(
        reliability="best_effort", durability="volatile", history="keep_last", depth=7)
    assert merged_qos(()).reliability == "reliable"
    assert merged_qos(({"reliability": "reliable", "durability": "transient_local", "depth": 0},)) == QosSpec(
        durability="transient_local", depth=10)  # depth unknown (0): the default depth
    # a foreign bag without recorded QoS plays with the default QoS
    write_foreign_bag(tmp_path / "foreign", n=5)
    node2 = _FakeNode()
    assert node2.play(BagReader(tmp_path / "foreign"), rate=100.0) == 10
    assert node2.pubs["/imu"].qos.depth == 10
    assert all(isinstance(d, bytes) for _, _, d in node.out + node2.out)  # raw CDR, never re-serialised
    with pytest.raises(ValueError, match="rate"):
        play_bag(_FakeNode(), BagReader(bag), rate=0.0)


def test_play_loop_and_synthetic_clock(tmp_path: Path) -> None:
    write_foreign_bag(tmp_path / "foreign", n=4)
    want = _expected(tmp_path / "foreign")
    node = _FakeNode()
    assert node.play(BagReader(tmp_path / "foreign"), rate=50.0, loop=True, max_loops=3, clock=True) == 3 * len(want)
    data = [(t, d) for _, t, d in node.out if t != "/clock"]
    assert data == [(t, d) for t, _, d in want] * 3
    clocks = [d for _, t, d in node.out if t == "/clock"]
    assert len(clocks) == 3 * len(want)  # one /clock (the log time) before every message
    assert [c.clock.sec * 1_000_000_000 + c.clock.nanosec for c in clocks[: len(want)]] == [lt for _, lt, _ in want]


@pytest.mark.parametrize("kind", ["graph", "foreign"])
def test_play_into_a_ros_graph(ros_graph: Any, tmp_path: Path, kind: str) -> None:  # noqa: F811 (fixture)
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from der_ros.contract_ros import message_class

    bag = tmp_path / "bag"
    if kind == "graph":
        record_env_bag(bag, episodes=5, max_episode_steps=6)
    else:  # rosbags-written, std_msgs/String + sensor_msgs/Imu, no recorded QoS
        write_foreign_bag(bag, n=30)
    want = _expected(bag)
    reader = BagReader(bag)
    node = ros_graph.probe.node
    lock = threading.Lock()
    got: list[tuple[float, str, bytes]] = []
    for topic, conn in reader.topics().items():
        rel = ReliabilityPolicy.BEST_EFFORT if topic == "/clock" else ReliabilityPolicy.RELIABLE
        qos = QoSProfile(depth=200, reliability=rel)

        def cb(data: bytes, topic: str = topic) -> None:
            with lock:
                got.append((time.monotonic(), topic, data))

        node.create_subscription(message_class(conn.msgtype), topic, cb, qos, raw=True)
    rate = 2.0 if kind == "graph" else 1.0
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_graph.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    argv = [sys.executable, "-m", "der_ros.cli", "bag", "play", str(bag), "--rate", str(rate),
            "--wait-subscribers", "20", "--delay", "0.5"]
    proc = NodeProcess("player", argv, env, tmp_path / "player.log")
    ros_graph.procs.append(proc)
    wait_for(lambda: proc.poll() is not None, timeout=40, what="the player to finish")
    assert proc.poll() == 0, proc.output()
    wait_for(lambda: len(got) >= len(want), timeout=5, what=f"{len(want)} messages (got {len(got)})")
    time.sleep(0.2)
    with lock:
        received = list(got)
    # every message, exactly once, in order per topic, bytes unchanged (DDS may pad the CDR
    # payload with up to 3 zero bytes to a multiple of 4: strip them before comparing)
    assert len(received) == len(want)
    for topic in {t for t, _, _ in want}:
        sent = [d for t, _, d in want if t == topic]
        recv = [d for _, t, d in received if t == topic]
        assert len(recv) == len(sent), topic
        for r, d in zip(recv, sent):
            assert r[: len(d)] == d and r[len(d):] == bytes(len(r) - len(d)) and len(r) - len(d) < 4, topic
    # the schedule (recorded gaps / rate) is checked exactly on a simulated clock above; wall-clock timing
    # through DDS is a benchmark's business, never a test threshold


def test_a_bag_with_other_types_on_our_topics_or_no_ros_messages_is_not_played(tmp_path: Path) -> None:
    """Our topic names with other types, or a JSON MCAP: an error naming what was found, nothing published."""
    from der_ros.bag.reader import BagError
    from der_ros.offline.export import build_transitions

    write_mistyped_bag(tmp_path / "mistyped", n=5)
    node = _FakeNode()
    with pytest.raises(BagError, match=r"/clock has type std_msgs/msg/String where rosgraph_msgs/msg/Clock was "
                                       r"expected; .*/state has type std_msgs/msg/String where sensor_msgs/msg/PointCloud2"):
        play_bag(node, BagReader(tmp_path / "mistyped"))
    assert node.out == []
    # the export names the types too (it used to say only "no state, reward topic")
    with pytest.raises(BagError, match=r"no state, reward topic in the bag of the expected type: /reward has type "
                                       r"std_msgs/msg/String where geometry_msgs/msg/Vector3Stamped was expected"):
        build_transitions(BagReader(tmp_path / "mistyped"))
    # a topic the user picks that is not ours still plays... none here; an empty choice is an error, not "0 published"
    with pytest.raises(BagError, match="nothing to play: none of --topics is in the bag"):
        play_bag(_FakeNode(), BagReader(tmp_path / "mistyped"), topics=["/elsewhere"])

    write_json_mcap(tmp_path / "telemetry.mcap")
    with pytest.raises(BagError, match="nothing to play: /telemetry is json-encoded, not ROS 2 CDR"):
        play_bag(_FakeNode(), BagReader(tmp_path / "telemetry.mcap"))


@pytest.mark.parametrize("kind", ["mistyped", "json"])
def test_der_replay_play_of_a_bag_it_cannot_play_exits_non_zero(ros_domain: int, tmp_path: Path, kind: str) -> None:  # noqa: F811
    import subprocess

    bag = tmp_path / ("bag" if kind == "mistyped" else "telemetry.mcap")
    write_mistyped_bag(bag) if kind == "mistyped" else write_json_mcap(bag)
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    done = subprocess.run([sys.executable, "-m", "der_ros.cli", "bag", "play", str(bag), "--rate", "100"], env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1, done.stdout + done.stderr
    want = "where rosgraph_msgs/msg/Clock was expected" if kind == "mistyped" else "json-encoded, not ROS 2 CDR"
    assert f"der bag play: error: {bag}" in done.stderr and want in done.stderr, done.stderr
    assert "published" not in done.stdout + done.stderr
