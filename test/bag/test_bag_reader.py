"""BagReader: agreement with the mcap reader, foreign writers, cut bags, corrupted bags, streaming."""

from __future__ import annotations

import shutil
import tracemalloc
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from bag_helpers import TS, msg_cmd, msg_reward, write_foreign_bag
from mcap.reader import make_reader

from der_ros.bag import mcap_records
from der_ros.bag.mcap_records import MSG
from der_ros.bag.reader import BagError, BagReader, DamagedChunkWarning, TruncatedBagWarning
from der_ros.bag.writer import BagWriter


def _small_bag(path: Path, n: int = 3000, compression: str | None = None, chunk_size: int = 16 * 1024) -> Path:
    """Reward and command messages with distinct stamps, several MCAP chunks."""
    w = BagWriter(path, compression=compression, chunk_size=chunk_size, flush_every_messages=10_000)
    w.add_topic("/reward", "geometry_msgs/msg/Vector3Stamped")
    w.add_topic("/lane_change_cmd", "sensor_msgs/msg/Joy")
    for i in range(n):
        t = i * 1_000_000
        if i % 2:
            w.write_message("/lane_change_cmd", t, msg_cmd(t, i % 3))
        else:
            w.write_message("/reward", t, msg_reward(t, float(i), i % 10 == 0, False))
    w.close()
    return path


def _mcap_file(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def _plain_mcap_messages(f: Path) -> list[tuple[str, int, bytes]]:
    with open(f, "rb") as fh:
        return [(c.topic, m.log_time, bytes(m.data)) for _s, c, m in make_reader(fh).iter_messages(log_time_order=False)]


def _ours(bag: Path) -> list[tuple[str, int, bytes]]:
    return [(m.topic, m.log_time, bytes(m.data)) for m in BagReader(bag).messages()]


@pytest.mark.parametrize("compression", [None, "zstd", "lz4"])
def test_same_messages_as_the_mcap_reader(tmp_path: Path, compression: str | None) -> None:
    bag = _small_bag(tmp_path / "b", compression=compression)
    ours = _ours(bag)
    assert len(ours) == 3000
    assert ours == _plain_mcap_messages(_mcap_file(bag))
    # decoding: values as written
    r = BagReader(bag)
    xs = [m.decode().vector.x for m in r.messages(["/reward"])]
    assert xs == [float(i) for i in range(0, 3000, 2)]
    assert r.summary_counts == {"/reward": 1500, "/lane_change_cmd": 1500}
    assert not r.truncated


def test_topic_filter_skips_other_topics(tmp_path: Path) -> None:
    bag = _small_bag(tmp_path / "b", n=100)
    msgs = list(BagReader(bag).messages(["/lane_change_cmd"]))
    assert {m.topic for m in msgs} == {"/lane_change_cmd"}
    assert [int(m.decode().buttons[0]) for m in msgs] == [i % 3 for i in range(1, 100, 2)]


def test_foreign_writers(tmp_path: Path) -> None:
    # rosbags' own rosbag2 writer (schemas/channels inside chunks, no CRCs)
    counts = write_foreign_bag(tmp_path / "rb", n=40)
    r = BagReader(tmp_path / "rb")
    assert {t: c.msgtype for t, c in r.topics().items()} == {"/chatter": "std_msgs/msg/String", "/imu": "sensor_msgs/msg/Imu"}
    msgs = list(r.messages())
    assert {t: sum(m.topic == t for m in msgs) for t in counts} == counts
    assert msgs[-2].decode().data == "hello 39"
    assert msgs[-1].decode().angular_velocity.z == 39.0
    # mcap-ros2-support's writer: a bare .mcap, "pkg/Type" schema names, no metadata.yaml, no QoS
    from mcap_ros2.writer import Writer

    f = tmp_path / "bare.mcap"
    with open(f, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef("std_msgs/String", "string data")
        for i in range(25):
            w.write_message("/talk", schema, {"data": f"m{i}"}, log_time=i, publish_time=i)
        w.finish()
    r = BagReader(f)
    assert r.metadata is None
    assert r.topics()["/talk"].msgtype == "std_msgs/msg/String"
    assert [m.decode().data for m in r.messages()] == [f"m{i}" for i in range(25)]


def test_custom_type_decoded_from_the_bag_schema(tmp_path: Path) -> None:
    """A type the Jazzy typestore lacks is registered from the schema text in the bag."""
    from mcap_ros2.writer import Writer

    f = tmp_path / "custom.mcap"
    msgdef = "float64 a\nmy_pkg/Inner inner\n" + "=" * 80 + "\nMSG: my_pkg/Inner\nint32[] values\n"
    with open(f, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef("my_pkg/Outer", msgdef)
        w.write_message("/custom", schema, {"a": 1.5, "inner": {"values": [1, 2, 3]}}, log_time=5)
        w.finish()
    (m,) = list(BagReader(f).messages())
    d = m.decode()
    assert d.a == 1.5 and list(d.inner.values) == [1, 2, 3]


def _cut_copy(src: Path, dst: Path, size: int, keep_metadata: bool) -> Path:
    dst.mkdir()
    data = _mcap_file(src).read_bytes()[:size]
    (dst / _mcap_file(src).name).write_bytes(data)
    if keep_metadata:
        shutil.copy(src / "metadata.yaml", dst / "metadata.yaml")  # stale: counts of the full bag
    return dst


@pytest.mark.parametrize("compression", [None, "zstd"])
def test_cut_bags_yield_every_complete_message_before_the_cut(tmp_path: Path, compression: str | None) -> None:
    bag = _small_bag(tmp_path / "full", n=3000, compression=compression)
    full = list(BagReader(bag).messages())
    full_bytes = [(m.topic, m.log_time, bytes(m.data)) for m in full]
    size = _mcap_file(bag).stat().st_size
    prev = -1
    for i, frac in enumerate((0.05, 0.33, 0.5, 0.71, 0.97)):
        cut = int(size * frac)
        d = _cut_copy(bag, tmp_path / f"cut{i}", cut, keep_metadata=i % 2 == 0)
        with pytest.warns(TruncatedBagWarning, match="truncated"):
            r = BagReader(d)
            got = [(m.topic, m.log_time, bytes(m.data)) for m in r.messages()]
        assert r.truncated
        assert got == full_bytes[: len(got)], "a cut bag must yield a prefix of the messages"
        assert len(got) >= prev
        prev = len(got)
        if compression is None:
            # uncompressed chunks: exactly the messages whose record ends before the cut
            expected = sum(1 for m in full if m.offset + 9 + 22 + len(m.data) <= cut)
            assert len(got) == expected, (frac, len(got), expected)
        else:
            assert len(got) > 0 or cut < 2000
    assert prev > 0.9 * len(full)


def test_cut_bag_without_metadata_and_cut_inside_record_header(tmp_path: Path) -> None:
    bag = _small_bag(tmp_path / "full", n=500)
    size = _mcap_file(bag).stat().st_size
    d = _cut_copy(bag, tmp_path / "c", size - 3, keep_metadata=False)  # loses the footer magic only
    with pytest.warns(TruncatedBagWarning):
        got = _ours(d)
    assert len(got) == 500  # every message is in the data section, before the summary
    d2 = _cut_copy(bag, tmp_path / "c2", 8 + 9 + 3, keep_metadata=False)  # inside the header record
    with pytest.warns(TruncatedBagWarning):
        assert _ours(d2) == []
    d3 = _cut_copy(bag, tmp_path / "c3", 5, keep_metadata=False)
    with pytest.raises(BagError, match="magic"):
        BagReader(d3)


def _read_all_decoded(bag: Path) -> list[tuple[str, int, bytes]]:
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedBagWarning)
        for m in BagReader(bag).messages():
            m.decode()
            out.append((m.topic, m.log_time, bytes(m.data)))
    return out


def _chunks(bag: Path) -> list[tuple[int, int]]:
    """(start, end) byte range of every chunk record of the bag's file, from its chunk index."""
    with open(_mcap_file(bag), "rb") as fh:
        summary = make_reader(fh).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in summary.chunk_indexes)


def _by_chunk(bag: Path) -> dict[tuple[int, int], list[tuple[str, int, bytes]]]:
    """The intact bag's messages grouped by the chunk that holds them."""
    ranges = _chunks(bag)
    out: dict[tuple[int, int], list[tuple[str, int, bytes]]] = {r: [] for r in ranges}
    for m in BagReader(bag).messages():
        (r,) = [r for r in ranges if r[0] <= m.offset < r[1]]
        out[r].append((m.topic, m.log_time, bytes(m.data)))
    return out


def _damaged_copy(bag: Path, dst: Path, pos: int, xor: int = 0xFF) -> Path:
    raw = bytearray(_mcap_file(bag).read_bytes())
    raw[pos] ^= xor
    dst.mkdir()
    (dst / _mcap_file(bag).name).write_bytes(bytes(raw))
    return dst


def _read_with_warnings(bag: Path) -> tuple[list[tuple[str, int, bytes]], list[str], BagReader]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = BagReader(bag)
        got = [(m.topic, m.log_time, bytes(m.data)) for m in reader.messages()]
    return got, [str(w.message) for w in caught if issubclass(w.category, DamagedChunkWarning)], reader


@pytest.mark.parametrize(("compression", "flips"), [("zstd", 1), (None, 2)])
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_a_damaged_chunk_is_skipped_and_the_rest_is_read(tmp_path: Path, compression: str | None, flips: int,
                                                         seed: int) -> None:  # fmt: skip
    """Seeded random damage inside one chunk that the CRC cannot place on one byte (a compressed
    chunk, or two damaged bytes): one warning naming the chunk's byte range and the messages it
    held; every message of every other chunk is read, exactly."""
    bag = _small_bag(tmp_path / "full", n=1500, compression=compression, chunk_size=4096)
    by_chunk = _by_chunk(bag)
    ranges = list(by_chunk)
    assert len(ranges) >= 5
    rng = np.random.default_rng(seed)
    start, end = ranges[int(rng.integers(len(ranges)))]
    raw = bytearray(_mcap_file(bag).read_bytes())
    # past the record header and the time fields (no CRC on those); two flips far enough apart
    # that no single byte explains them
    for pos in rng.choice(np.arange(start + 9 + 28, end), size=flips, replace=False):
        raw[int(pos)] ^= int(rng.integers(1, 256))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / _mcap_file(bag).name).write_bytes(bytes(raw))
    got, warned, reader = _read_with_warnings(bad)
    intact = [m for r in ranges if r != (start, end) for m in by_chunk[r]]
    assert got == intact
    assert len(got) + len(by_chunk[(start, end)]) == 1500
    assert len(warned) == 1 and f"bytes {start}-{end}" in warned[0], warned
    assert f"{len(by_chunk[(start, end)])} messages lost" in warned[0]
    (damage,) = reader.damaged
    assert (damage.start, damage.end, damage.messages_lost) == (start, end, len(by_chunk[(start, end)]))
    # a second pass (der bag info scans, then exports) reports the same chunk once
    assert [(m.topic, m.log_time, bytes(m.data)) for m in reader.messages()] == intact
    assert len(reader.damaged) == 1


def _with_offsets(bag: Path) -> list[tuple[str, int, bytes, int, int]]:
    """Every message of an intact bag with the byte range of its record (an uncompressed bag)."""
    return [(m.topic, m.log_time, bytes(m.data), m.offset, m.offset + 9 + MSG.size + len(m.data))
            for m in BagReader(bag).messages()]


@pytest.mark.parametrize("seed", range(8))
def test_one_flipped_byte_in_an_uncompressed_chunk_costs_only_its_record(tmp_path: Path, seed: int) -> None:
    """Issue 45, finding 5: a damaged byte in a message record of an uncompressed chunk (its CRC
    fails) loses that one message; the chunk's other records are read as written, one warning says
    where the byte is and counts the one message lost."""
    bag = _small_bag(tmp_path / "full", n=1500, chunk_size=4096)
    intact = _with_offsets(bag)
    ranges = _chunks(bag)
    rng = np.random.default_rng(seed)
    start, end = ranges[int(rng.integers(1, len(ranges)))]
    records = [(o0, o1) for *_m, o0, o1 in intact if start <= o0 < end]
    assert len(records) > 20
    o0, o1 = records[int(rng.integers(len(records)))]
    pos = int(rng.integers(o0, o1))  # header, channel, times or payload of one message record
    got, warned, reader = _read_with_warnings(_damaged_copy(bag, tmp_path / "bad", pos, xor=int(rng.integers(1, 256))))
    assert got == [m[:3] for m in intact if m[3] != o0]
    (damage,) = reader.damaged
    assert (damage.start, damage.end, damage.damaged_at, damage.dropped, damage.messages_lost) == (start, end, pos,
                                                                                                    (o0, o1), 1)
    assert damage.bytes_lost == o1 - o0
    assert len(warned) == 1 and f"damaged byte at {pos}" in warned[0] and "1 messages lost" in warned[0], warned
    assert [(m.topic, m.log_time, bytes(m.data)) for m in reader.messages()] == got  # a second pass: same, one report
    assert len(reader.damaged) == 1


def test_a_flipped_crc_field_loses_nothing(tmp_path: Path) -> None:
    """The damaged byte is in the chunk's stored CRC: every record is intact and read; reported, 0 lost."""
    bag = _small_bag(tmp_path / "full", n=1500, chunk_size=4096)
    intact = [m[:3] for m in _with_offsets(bag)]
    start, end = _chunks(bag)[2]
    for i in range(4):
        pos = start + 9 + 24 + i  # record header, start/end times, uncompressed size, then the CRC
        got, warned, reader = _read_with_warnings(_damaged_copy(bag, tmp_path / f"crc{i}", pos, xor=0x5A))
        assert got == intact
        (damage,) = reader.damaged
        assert (damage.damaged_at, damage.dropped, damage.messages_lost, damage.bytes_lost) == (pos, None, 0, 0)
        assert len(warned) == 1 and "0 messages lost" in warned[0]


def test_locate_byte_error_finds_every_single_byte_and_refuses_two() -> None:
    """The CRC walk against brute force on random records: every single damaged byte is placed with
    its xor; two damaged bytes are not explained by one."""
    rng = np.random.default_rng(7)
    data = rng.integers(0, 256, 3000, dtype=np.uint8).tobytes()
    crc = zlib.crc32(data)
    for pos in rng.integers(0, len(data), 40).tolist() + [0, len(data) - 1]:
        xor = int(rng.integers(1, 256))
        bad = bytearray(data)
        bad[pos] ^= xor
        assert mcap_records.locate_byte_error(bytes(bad), crc) == (pos, xor)
        bad[(pos + 1000) % len(data)] ^= 0x81
        assert mcap_records.locate_byte_error(bytes(bad), crc) is None
    assert mcap_records.locate_byte_error(data, crc) is None
    assert mcap_records.locate_byte_error(data, crc ^ 0x00A50000) == (-3, 0xA5)  # byte 2 of the stored CRC


def test_a_damaged_chunk_header_is_stepped_over_with_the_chunk_index(tmp_path: Path) -> None:
    """A flip in a chunk's record length breaks the record framing: the summary's chunk index
    still says where the chunk ends."""
    bag = _small_bag(tmp_path / "full", n=1500, chunk_size=4096)
    by_chunk = _by_chunk(bag)
    (start, end) = list(by_chunk)[2]
    for name, pos in (("length", start + 5), ("opcode", start)):
        got, warned, _ = _read_with_warnings(_damaged_copy(bag, tmp_path / name, pos))
        assert got == [m for r, ms in by_chunk.items() if r != (start, end) for m in ms], name
        assert len(warned) == 1 and f"bytes {start}-{end}" in warned[0] and "chunk index" in warned[0], warned


@pytest.mark.slow
def test_flipped_bytes_anywhere_skip_a_chunk_or_give_a_bag_error(tmp_path: Path) -> None:
    """Flips all over the file: the reader skips the chunk they damaged (and reads the others
    exactly), or raises a BagError naming file and offset, or the flip hit bytes a streamed read
    does not use and the messages are the original ones -- never a traceback, never wrong data."""
    bag = _small_bag(tmp_path / "full", n=600, chunk_size=4096)
    by_chunk = _by_chunk(bag)
    original = [m for ms in by_chunk.values() for m in ms]
    offsets = _with_offsets(bag)
    placed = 0
    raw = _mcap_file(bag).read_bytes()
    rng = np.random.default_rng(0)
    positions = sorted(set(rng.integers(0, len(raw), 150).tolist()) | {0, 3, 8, 9, 17, 40, len(raw) - 4})
    skipped = errors = 0
    for pos in positions:
        d = _damaged_copy(bag, tmp_path / f"flip{pos}", pos)
        try:
            got, warned, reader = _read_with_warnings(d)
            for m in got:
                TS.deserialize_cdr(m[2], "geometry_msgs/msg/Vector3Stamped" if m[0] == "/reward" else "sensor_msgs/msg/Joy")
        except BagError as exc:
            errors += 1
            assert str(d / _mcap_file(bag).name) in str(exc) and "offset" in str(exc), str(exc)
            continue
        if reader.damaged:
            skipped += 1
            lost = {(c.start, c.end) for c in reader.damaged if c.damaged_at is None}
            dropped = {c.dropped[0] for c in reader.damaged if c.dropped is not None}
            placed += sum(c.damaged_at is not None for c in reader.damaged)
            # a chunk skipped whole, or one message record dropped (the one the CRC placed the flip in)
            assert got == [m[:3] for m in offsets if m[3] not in dropped
                           and not any(a <= m[3] < b for a, b in lost)], pos
            assert len(got) + sum(c.messages_lost or 0 for c in reader.damaged) == len(original), pos
            assert len(warned) == len(reader.damaged)
        else:
            assert got == original, f"flip at {pos} changed the messages without a warning"
    assert skipped > len(positions) // 3  # most of the file is chunk data protected by CRCs
    assert placed > len(positions) // 3  # and most of those flips cost one record, not the chunk
    assert errors + skipped < len(positions)


@pytest.mark.slow
def test_reader_streams_without_materialising_messages(tmp_path: Path) -> None:
    n = 100_000
    w = BagWriter(tmp_path / "big", flush_every_messages=1_000_000, flush_every_seconds=3600.0)
    w.add_topic("/reward", "geometry_msgs/msg/Vector3Stamped")
    payload = TS.serialize_cdr(msg_reward(0, 1.0, False, False), "geometry_msgs/msg/Vector3Stamped")
    for i in range(n):
        w.write("/reward", i, payload)
    w.close()
    bag_bytes = _mcap_file(tmp_path / "big").stat().st_size
    r = BagReader(tmp_path / "big")
    tracemalloc.start()
    try:
        count = 0
        total = 0.0
        nbytes = 0
        for m in r.messages():
            nbytes += len(m.data)
            if count % 20 == 0:  # decoding is per message: a sample shows it keeps nothing either
                total += m.decode().vector.x
            count += 1
        _cur, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == n and total == float(n // 20) and nbytes == n * len(payload)
    # one ~512 KiB chunk (raw + parsed) at a time; a materialised list would need > bag size
    assert bag_bytes > 6_000_000
    assert peak < 4_000_000, f"peak {peak / 1e6:.1f} MB while streaming a {bag_bytes / 1e6:.1f} MB bag"


def test_missing_or_unknown_paths(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such bag"):
        BagReader(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="no .mcap file"):
        BagReader(tmp_path / "empty")
    (tmp_path / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(BagError, match="bad magic"):
        BagReader(tmp_path / "x.mcap")



def test_split_bag_and_unchunked_mcap(tmp_path: Path) -> None:
    w = BagWriter(tmp_path / "split", max_file_messages=100)
    w.add_topic("/reward", "geometry_msgs/msg/Vector3Stamped")
    for i in range(350):
        w.write_message("/reward", i, msg_reward(i, float(i), False, False))
    w.close()
    assert len(list((tmp_path / "split").glob("*.mcap"))) == 4
    xs = [m.decode().vector.x for m in BagReader(tmp_path / "split").messages()]
    assert xs == [float(i) for i in range(350)]
    (tmp_path / "split" / "metadata.yaml").unlink()  # file order then comes from the names (_0 < _1 < ... < _10)
    assert [m.decode().vector.x for m in BagReader(tmp_path / "split").messages()] == xs
    # an MCAP file without chunks (messages as top-level records)
    from mcap.writer import Writer

    f = tmp_path / "flat.mcap"
    with open(f, "wb") as fh:
        mw = Writer(fh, use_chunking=False)
        mw.start(profile="ros2", library="test")
        sid = mw.register_schema("geometry_msgs/msg/Vector3Stamped", "ros2msg", b"")
        cid = mw.register_channel("/reward", "cdr", sid)
        for i in range(20):
            mw.add_message(cid, log_time=i, publish_time=i, sequence=i,
                           data=TS.serialize_cdr(msg_reward(i, float(i), False, False), "geometry_msgs/msg/Vector3Stamped"))
        mw.finish()
    assert [m.decode().vector.x for m in BagReader(f).messages()] == [float(i) for i in range(20)]
    # cut inside a top-level message record
    cut = tmp_path / "flatcut.mcap"
    cut.write_bytes(f.read_bytes()[: 700])
    with pytest.warns(TruncatedBagWarning):
        xs_cut = [m.decode().vector.x for m in BagReader(cut).messages()]
    assert 0 < len(xs_cut) < 20 and xs_cut == [float(i) for i in range(len(xs_cut))]


@pytest.mark.slow
def test_bag_of_a_killed_writer_process(tmp_path: Path) -> None:
    """SIGKILL a process writing through BagWriter: everything flushed is read back, in order."""
    import signal
    import subprocess
    import sys
    import time

    import yaml

    bag = tmp_path / "killed"
    script = f"""
import sys, time
sys.path.insert(0, {str(Path(__file__).parents[1])!r})
from der_ros.bag.writer import BagWriter
from bag_helpers import msg_reward
w = BagWriter({str(bag)!r}, flush_every_messages=50)
w.add_topic("/reward", "geometry_msgs/msg/Vector3Stamped")
i = 0
while True:
    w.write_message("/reward", i, msg_reward(i, float(i), False, False))
    i += 1
    if i == 400:
        print("ready", flush=True)
    time.sleep(0.0002)
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
        time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    flushed = meta["message_count"]
    with pytest.warns(TruncatedBagWarning, match="footer"):
        xs = [m.decode().vector.x for m in BagReader(bag).messages()]
    assert len(xs) >= flushed >= 400
    assert xs == [float(i) for i in range(len(xs))]


@pytest.mark.slow
def test_flipped_bytes_in_a_bag_without_crcs_never_escape_as_other_errors(tmp_path: Path) -> None:
    """rosbags writes no CRCs: a flip may go unnoticed in a payload, but never crashes the reader;
    a chunk whose records stop parsing is skipped (minus the messages read before the damage)."""
    write_foreign_bag(tmp_path / "rb", n=30)
    f = next((tmp_path / "rb").glob("*.mcap"))
    raw = f.read_bytes()
    rng = np.random.default_rng(1)
    errors = skipped = 0
    for pos in sorted(set(rng.integers(0, len(raw), 80).tolist())):
        bad = bytearray(raw)
        bad[pos] ^= 0xFF
        d = tmp_path / f"flip{pos}"
        d.mkdir()
        (d / f.name).write_bytes(bytes(bad))
        try:
            got, warned, reader = _read_with_warnings(d)
        except BagError as exc:
            errors += 1
            assert str(d / f.name) in str(exc)
            continue
        if reader.damaged:
            skipped += 1
            (damage,) = reader.damaged
            assert len(warned) == 1 and damage.messages_lost == 60 - len(got)
    assert errors > 0 and skipped > 0


def test_bag_with_no_messages(tmp_path: Path) -> None:
    w = BagWriter(tmp_path / "empty")
    w.add_topic("/reward", "geometry_msgs/msg/Vector3Stamped")
    w.flush()  # what a recorder killed before the first message leaves (no footer)
    d = tmp_path / "killed"
    d.mkdir()
    (d / "killed_0.mcap").write_bytes(next((tmp_path / "empty").glob("*.mcap")).read_bytes())
    meta = (tmp_path / "empty" / "metadata.yaml").read_text()
    (d / "metadata.yaml").write_text(meta.replace("empty_0.mcap", "killed_0.mcap"))
    w.close()
    assert list(BagReader(tmp_path / "empty").messages()) == []
    assert set(BagReader(tmp_path / "empty").topics()) == {"/reward"}
    with pytest.warns(TruncatedBagWarning):
        r = BagReader(d)
        assert list(r.messages()) == []
    # the cut file holds no channel record (the writer's first chunk never came): metadata.yaml's topics
    assert set(r.topics()) == {"/reward"}
    assert r.topics()["/reward"].msgtype == "geometry_msgs/msg/Vector3Stamped"
    (d / "killed_0.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="empty bag"):
        BagReader(d)


def test_der_graph_reports_a_killed_recorders_bag_in_one_log_line(tmp_path: Path, caplog, recwarn) -> None:
    """Issue 45: after a recorder kill, der graph printed Python's raw two-line ``warnings`` output."""
    import logging

    from der_ros.graph.run_summary import snapshot_from_bag

    bag = _small_bag(tmp_path / "full", n=300)
    cut = _cut_copy(bag, tmp_path / "cut", _mcap_file(bag).stat().st_size // 2, keep_metadata=False)
    with caplog.at_level(logging.WARNING, logger="der.graph"):
        snapshot_from_bag(cut, None)
    assert not [w for w in recwarn if issubclass(w.category, TruncatedBagWarning)]  # nothing reaches warnings
    lines = [r.getMessage() for r in caplog.records if "truncated" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0] and "recorder killed?" in lines[0]
