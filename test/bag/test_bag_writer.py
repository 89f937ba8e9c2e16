"""BagWriter: rosbag2-MCAP layout, readability by rosbags and mcap (with CRCs), flush/kill bounds."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.rosbag2 import Reader

from der_ros.bag.reader import TruncatedBagWarning
from der_ros.bag.writer import (
    EPISODES_KEY,
    FINALIZED_KEY,
    BagWriter,
    BagWriterError,
    jazzy_typestore,
    read_episode_summary,
    recover_bag,
)
from der_ros.contract import QosSpec

TS = jazzy_typestore()
T = TS.types


def joy(i: int) -> object:
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=7), frame_id="f")
    return T["sensor_msgs/msg/Joy"](header=header, axes=np.array([0.5 * i], dtype=np.float32),
                                    buttons=np.array([i % 3], dtype=np.int32))


def string(text: str) -> object:
    return T["std_msgs/msg/String"](data=text)


def read_metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def stream_messages(mcap_path: Path) -> tuple[list[Message], bool]:
    """Messages a streaming reader gets (with CRC checks) and whether the file ended cleanly."""
    out: list[Message] = []
    with open(mcap_path, "rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Message):
                    out.append(rec)
        except Exception:  # truncated file: the reader stops at the cut
            return out, False
    return out, True


def test_round_trip_rosbags_and_mcap(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag, flush_every_messages=7) as w:
        w.add_topic("lane_change_cmd", "sensor_msgs/msg/Joy")  # table QoS: RELIABLE KEEP_LAST 10
        w.add_topic("/clock", "rosgraph_msgs/msg/Clock")  # table QoS: BEST_EFFORT depth 1
        w.add_topic("/chatter", "std_msgs/msg/String", QosSpec(durability="transient_local", depth=3))
        expected = []
        for i in range(40):
            t = 1_000 + 10 * i
            if i % 4 == 0:
                w.write_message("/chatter", t, string(f"m{i}"), publish_time_ns=t - 3)
                expected.append(("/chatter", t))
            else:
                w.write_message("lane_change_cmd", t, joy(i))
                expected.append(("/lane_change_cmd", t))
        clock = T["rosgraph_msgs/msg/Clock"](clock=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0))
        raw = TS.serialize_cdr(clock, "rosgraph_msgs/msg/Clock")
        w.write("/clock", 2_000, raw)
        expected.append(("/clock", 2_000))
    assert w.closed

    meta = read_metadata(bag)
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["message_count"] == 41
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == {"/lane_change_cmd": 30, "/clock": 1, "/chatter": 10}
    assert meta["duration"]["nanoseconds"] == 2_000 - 1_000

    with Reader(bag) as r:
        conns = {c.topic: c for c in r.connections}
        assert conns["/clock"].ext.offered_qos_profiles[0].reliability == QosReliability.BEST_EFFORT
        assert conns["/chatter"].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
        assert conns["/lane_change_cmd"].ext.offered_qos_profiles[0].depth == 10
        got = [(c.topic, t) for c, t, _ in r.messages()]
        assert got == sorted(expected, key=lambda x: x[1])
        for c, t, data in r.messages(connections=[conns["/lane_change_cmd"]]):
            msg = TS.deserialize_cdr(data, c.msgtype)
            i = (t - 1_000) // 10
            assert msg.header.stamp.sec == i and int(msg.buttons[0]) == i % 3

    mcap_path = bag / "bag_0.mcap"
    with open(mcap_path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 41
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for ch in summary.channels.values():
            qos = yaml.safe_load(ch.metadata["offered_qos_profiles"])
            assert isinstance(qos, list) and qos[0]["history"] == "keep_last"
        joy_schema = next(s for s in summary.schemas.values() if s.name == "sensor_msgs/msg/Joy")
        assert b"MSG: std_msgs/Header" in joy_schema.data  # dependencies appended as rosbag2 does
        msgs = list(reader.iter_messages())
        assert len(msgs) == 41
        chatter = [m for _, ch, m in msgs if ch.topic == "/chatter"]
        assert all(m.publish_time == m.log_time - 3 for m in chatter)
        assert [m.sequence for m in chatter] == list(range(10))
        names = [m.name for m in reader.iter_metadata()]
        assert "rosbag2" in names
    # every chunk CRC, and the data-section CRC, verified by the streaming reader too
    streamed, clean = stream_messages(mcap_path)
    assert clean and len(streamed) == 41


def test_zstd_and_lz4_compression_round_trip(tmp_path: Path) -> None:
    for comp in ("zstd", "lz4"):
        bag = tmp_path / comp
        with BagWriter(bag, compression=comp) as w:
            w.add_topic("/s", "std_msgs/msg/String")
            for i in range(100):
                w.write_message("/s", i + 1, string("x" * 200))
        with open(bag / f"{comp}_0.mcap", "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            chunk_comp = {ci.compression for ci in reader.get_summary().chunk_indexes}
            assert chunk_comp == {comp}
            assert sum(1 for _ in reader.iter_messages()) == 100
        with Reader(bag) as r:
            assert [TS.deserialize_cdr(d, c.msgtype).data for c, _, d in r.messages()] == ["x" * 200] * 100


@pytest.mark.slow
def test_a_long_recording_does_not_grow_the_writers_memory(tmp_path: Path) -> None:
    """Memory per recorded step is flat: every episode event used to stay in memory for the bag's summary (~60 B per
    decision step, the recorder's creep on a 30k-step run); now the flushed ones live only in episodes.jsonl. And
    the MCAP chunk index of every finished chunk (~0.7 kB each; a chunk is finished at every flush) waits in a
    temporary file for the summary (chunk_index_spill), where it was kept in memory (~15 B per step)."""
    import gc
    import tracemalloc

    w = BagWriter(tmp_path / "long", flush_every_messages=10**9, flush_every_seconds=1e9)
    topics = ("/state", "/reward", "/lane_change_cmd", "/clock")
    for topic, msgtype in zip(topics, ("sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/Vector3Stamped",
                                       "sensor_msgs/msg/Joy", "rosgraph_msgs/msg/Clock")):  # fmt: skip
        w.add_topic(topic, msgtype)
    payload = bytes(40)

    def record(steps: range) -> None:
        for k in steps:  # a decision step: four messages; an episode of 25 steps: two events
            ts = 10**9 + k * 5 * 10**8
            for topic in topics:
                w.write(topic, ts, payload)
            if k % 25 == 0:
                w.mark_episode(ts, episode=k // 25, event="start")
            elif k % 25 == 24:
                w.mark_episode(ts, episode=k // 25, event="collision", steps=25, ret=-1.5, lane_changes=3)
            if k % 50 == 49:
                w.flush()  # episode events go to episodes.jsonl at a flush; every flush finishes a chunk

    record(range(0, 2000))  # allocations of first use (schemas, buffers) before the measurement
    tracemalloc.start()
    try:
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        record(range(2000, 12000))
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    w.close()
    assert grown / 10_000 < 2, f"{grown / 10_000:.1f} B per step"  # was ~60, then ~15 with the chunk indexes
    events = read_episode_summary(tmp_path / "long")
    assert len(events) == 2 * 12000 // 25 and events[-1]["episode"] == 12000 // 25 - 1
    with open(tmp_path / "long" / "long_0.mcap", "rb") as f:  # the summary record still holds every event
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        summary = reader.get_summary()
    assert json.loads(meta[EPISODES_KEY]["episodes"]) == events
    # ... and every chunk's index, which the spill kept out of memory: an indexed read sees every message
    assert summary is not None and len(summary.chunk_indexes) == 12000 // 50
    assert summary.statistics.chunk_count == len(summary.chunk_indexes)
    offsets = [c.chunk_start_offset for c in summary.chunk_indexes]
    assert offsets == sorted(offsets) and all(c.message_index_offsets for c in summary.chunk_indexes)
    with open(tmp_path / "long" / "long_0.mcap", "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages(topics=["/clock"])) == 12000


def test_episode_marks_and_summary(tmp_path: Path) -> None:
    bag = tmp_path / "ep"
    with BagWriter(bag) as w:
        w.mark_episode(100, episode=0, event="start")
        w.mark_episode(900, episode=0, event="collision", steps=8, ret=-3.25, lane_changes=2, mean_speed=7.5)
        w.mark_episode(1000, episode=1, event="start")
        w.flush()
        during = read_metadata(bag)
        assert during["custom_data"][FINALIZED_KEY] == "false"
        assert during["custom_data"]["der_ros/episode_events"] == "3"
        assert len(read_episode_summary(bag)) == 3  # on disk before close
        w.mark_episode(2000, episode=1, event="success", steps=10, ret=4.0)
    assert read_metadata(bag)["custom_data"]["der_ros/episode_events"] == "4"
    episodes = read_episode_summary(bag)
    assert [(e["episode"], e["event"]) for e in episodes] == [(0, "start"), (0, "collision"), (1, "start"), (1, "success")]
    assert episodes[1]["return"] == -3.25 and episodes[1]["steps"] == 8 and episodes[1]["lane_changes"] == 2
    with Reader(bag) as r:
        msgs = [TS.deserialize_cdr(d, c.msgtype) for c, _, d in r.messages()]
    assert [m.status[0].message for m in msgs] == ["start", "collision", "start", "success"]
    assert msgs[1].status[0].level == 1  # WARN, like the bridge
    assert {kv.key: kv.value for kv in msgs[3].status[0].values}["return"] == "4.0"
    with open(bag / "ep_0.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f, validate_crcs=True).iter_metadata()}
    assert json.loads(meta[EPISODES_KEY]["episodes"]) == episodes
    with pytest.raises(BagWriterError, match="event"):
        BagWriter(tmp_path / "x").mark_episode(1, episode=0, event="crash")


def test_split_into_files(tmp_path: Path) -> None:
    bag = tmp_path / "split"
    with BagWriter(bag, max_file_messages=5) as w:
        w.add_topic("/s", "std_msgs/msg/String")
        for i in range(12):
            w.write_message("/s", i + 1, string(str(i)))
    meta = read_metadata(bag)
    assert meta["relative_file_paths"] == ["split_0.mcap", "split_1.mcap", "split_2.mcap"]
    assert [f["message_count"] for f in meta["files"]] == [5, 5, 2]
    with Reader(bag) as r:
        assert [TS.deserialize_cdr(d, c.msgtype).data for c, _, d in r.messages()] == [str(i) for i in range(12)]


def test_time_based_flush_rewrites_metadata(tmp_path: Path) -> None:
    w = BagWriter(tmp_path / "t", flush_every_messages=10_000, flush_every_seconds=0.3)
    w.add_topic("/s", "std_msgs/msg/String")
    w.write_message("/s", 1, string("a"))
    assert read_metadata(w.path)["message_count"] == 0  # still in the open chunk
    time.sleep(0.35)
    assert w.maybe_flush() is True
    assert read_metadata(w.path)["message_count"] == 1
    assert w.maybe_flush() is False  # nothing pending
    streamed, clean = stream_messages(w.path / "t_0.mcap")
    assert not clean and [m.log_time for m in streamed] == [1]
    w.close()


def test_bad_use_is_reported(tmp_path: Path) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(BagWriterError, match="not overwriting"):
        BagWriter(tmp_path / "full")
    with pytest.raises(BagWriterError, match="compression"):
        BagWriter(tmp_path / "c", compression="bz2")
    w = BagWriter(tmp_path / "w")
    with pytest.raises(BagWriterError, match="add_topic"):
        w.write("/nope", 1, b"")
    w.add_topic("/a", "std_msgs/msg/String")
    w.add_topic("a", "std_msgs/msg/String")  # same again: fine
    with pytest.raises(BagWriterError, match="already has type"):
        w.add_topic("/a", "sensor_msgs/msg/Joy")
    with pytest.raises(BagWriterError, match="typestore"):
        w.add_topic("/b", "no_pkg/msg/Nothing")
    w.close()
    with pytest.raises(BagWriterError, match="closed"):
        w.write("/a", 1, b"")


_KILL_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys
    from der_ros.bag.writer import BagWriter, jazzy_typestore
    T = jazzy_typestore().types
    w = BagWriter(sys.argv[1], flush_every_messages=int(sys.argv[2]), flush_every_seconds=3600)
    w.add_topic("/s", "std_msgs/msg/String")
    for i in range(int(sys.argv[3])):
        w.write_message("/s", 1000 + i, T["std_msgs/msg/String"](data=str(i)))
        if i % 10 == 0:
            w.mark_episode(1000 + i, episode=i // 10, event="start")
    sys.stdout.write("written\\n"); sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


@pytest.mark.slow
def test_sigkill_loses_at_most_the_unflushed_tail(tmp_path: Path) -> None:
    bag = tmp_path / "killed"
    flush_every, total = 16, 150
    proc = subprocess.run([sys.executable, "-c", _KILL_SCRIPT, str(bag), str(flush_every), str(total)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL and "written" in proc.stdout
    meta = read_metadata(bag)
    assert meta["custom_data"][FINALIZED_KEY] == "false"
    flushed = meta["message_count"]
    assert total + total // 10 - flushed < flush_every  # the lost tail is shorter than one flush period
    streamed, clean = stream_messages(bag / "killed_0.mcap")
    assert not clean  # no footer
    assert len(streamed) == flushed
    strings = [m for m in streamed if m.channel_id == streamed[0].channel_id]
    assert [TS.deserialize_cdr(m.data, "std_msgs/msg/String").data for m in strings] == [
        str(i) for i in range(len(strings))]
    n_marks = len(streamed) - len(strings)
    assert [e["episode"] for e in read_episode_summary(bag)] == list(range(n_marks))  # summary = flushed marks
    assert meta["custom_data"]["der_ros/episode_events"] == str(n_marks)
    # recover_bag makes a finalised copy that rosbags and the seeking mcap reader accept
    fixed = tmp_path / "fixed"
    with pytest.warns(TruncatedBagWarning, match="truncated"):
        assert recover_bag(bag, fixed) == flushed
    with Reader(fixed) as r:
        got = [(c.topic, t, bytes(d)) for c, t, d in r.messages()]
    assert got == [(("/s" if m.channel_id == streamed[0].channel_id else "/episode"), m.log_time, m.data)
                   for m in streamed]
    assert read_episode_summary(fixed) == read_episode_summary(bag)
    assert read_metadata(fixed)["custom_data"][FINALIZED_KEY] == "true"
    with open(bag / "killed_0.mcap", "rb") as f:  # a seeking reader needs the footer
        with pytest.raises(Exception):  # noqa: B017 - any error type: the file has no footer
            list(make_reader(f).iter_messages())
    assert os.path.getsize(bag / "killed_0.mcap") > 0


def test_recover_bag_steps_over_a_damaged_chunk(tmp_path: Path) -> None:
    """recover_bag copies what the reader reads: a damaged chunk in the middle costs only its own
    messages (streaming with CRC checks stops there and loses everything after it)."""
    src = tmp_path / "src"
    with BagWriter(src, chunk_size=2048, flush_every_messages=10_000) as w:
        w.add_topic("/s", "std_msgs/msg/String")
        for i in range(400):
            w.write_message("/s", i, string(f"message {i:04d}"))
    f = next(src.glob("*.mcap"))
    with open(f, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    target = chunks[len(chunks) // 2]
    raw = bytearray(f.read_bytes())
    raw[target.chunk_start_offset + target.chunk_length - 20] ^= 0x10  # inside the chunk's records
    f.write_bytes(bytes(raw))
    streamed, _ = stream_messages(f)
    assert len(streamed) < 400 // 2 + 50  # the streaming reader stops at the damaged chunk
    with pytest.warns(UserWarning, match=rf"bytes {target.chunk_start_offset}-{target.chunk_start_offset + target.chunk_length}"):
        copied = recover_bag(src, tmp_path / "fixed")
    with Reader(tmp_path / "fixed") as r:
        texts = [TS.deserialize_cdr(d, c.msgtype).data for c, _t, d in r.messages()]
    lost = 400 - copied
    assert 0 < lost < 60 and len(texts) == copied
    assert texts == [f"message {i:04d}" for i in range(400) if f"message {i:04d}" in set(texts)]
    assert texts[-1] == "message 0399"  # everything after the damaged chunk was copied
