"""ROS-free rosbag2 (MCAP storage) writer that stays readable when its process is killed.

Layout of a bag directory ``<dir>/`` (what ``ros2 bag record -s mcap`` makes, metadata version 9):

* ``<dir>/<name>_0.mcap`` (``_1``, ``_2``... when a split limit is set): profile ``ros2``,
  schema encoding ``ros2msg`` (message definitions with their dependencies, from the
  ``rosbags`` ROS2_JAZZY typestore), message encoding ``cdr``, channel metadata
  ``offered_qos_profiles`` (rosbag2 YAML). ``log_time`` is the stamp given to :meth:`write`
  (the recorder's receive time), ``publish_time`` the optional second stamp.
* ``<dir>/metadata.yaml``: rosbag2 bag information (topics with message counts, QoS, type
  hashes, files, duration), rewritten atomically (tmp + rename) **at every flush** and at close.

Why this design
  MCAP chunks are written only when finished, so a process killed between flushes loses the
  unfinished chunk and nothing before it. :meth:`flush` finishes the chunk, flushes the file
  and rewrites ``metadata.yaml`` with the counts *of what is on disk*; the writer flushes
  itself every ``flush_every_messages`` messages or ``flush_every_seconds`` seconds
  (checked on every write and by :meth:`maybe_flush`, which the recorder calls from a timer
  so a quiet topic does not hold its last messages in memory). A SIGKILL therefore loses at
  most the messages after the last flush. Such a bag has no MCAP footer/summary: streaming
  readers (``mcap.stream_reader.StreamReader``, our ``BagReader``) read it up to the cut, and its
  ``metadata.yaml`` already matches the flushed part (``custom_data: der_ros/finalized:
  'false'``); :func:`recover_bag` copies it into a finalised bag (like ``ros2 bag reindex``).
  :meth:`close` writes the footer, summary and statistics, a ``rosbag2`` MCAP metadata record,
  and the final ``metadata.yaml`` with ``der_ros/finalized: 'true'``.

Episodes
  The canonical episode record is the graph's ``episode`` topic (``diagnostic_msgs/msg/
  DiagnosticArray``, one status named ``episode`` per event, see ``docs/architecture.md``),
  recorded like any topic. :meth:`mark_episode` writes such a message (used by tools that
  write bags without a bridge). Every ``episode`` event written, by either path, is also
  collected into a bag-level summary, one JSON object per event (``t_ns`` log time,
  ``stamp_ns`` header stamp = sim time, ``event``, ``episode``, ``steps``, ``return``,
  ``lane_changes``, ``mean_speed``): appended to ``<dir>/episodes.jsonl`` at every flush (so a
  killed bag has it up to the last flush; :func:`read_episode_summary` reads it) and stored as
  the MCAP metadata record ``der_ros/episodes`` at close. ``metadata.yaml`` ``custom_data``
  carries only the count (``der_ros/episode_events``) so it stays small on long runs.
  Offline tools can split on the topic or on the summary without ROS.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapFileWriter

from der_ros.bag.chunk_index_spill import spill_chunk_indexes
from der_ros.bag.reader import BagReader
from der_ros.contract import (
    EPISODE,
    EPISODE_COLLISION,
    EPISODE_EVENTS,
    EPISODE_STATUS,
    RELIABLE_VOLATILE,
    QosSpec,
    episode_values,
    format_value,
    parse_episode_events,
    topic_by_name,
    topic_spec,
)
from der_ros.yaml_loader import load_yaml_text

__all__ = [
    "BagWriter",
    "BagWriterError",
    "FINALIZED_KEY",
    "EPISODES_KEY",
    "EPISODES_FILE",
    "read_episode_summary",
    "recover_bag",
    "qos_profiles_to_yaml",
    "episode_events_from_diagnostic_array",
    "jazzy_typestore",
]

log = logging.getLogger(__name__)

#: metadata.yaml custom_data key: "true" once close() ran, "false" while writing / after a kill.
FINALIZED_KEY = "der_ros/finalized"
#: MCAP metadata record name (written at close, key ``episodes``: JSON list) of the episode summary;
#: metadata.yaml ``custom_data`` has ``der_ros/episode_events`` (count) and ``der_ros/episodes_file``.
EPISODES_KEY = "der_ros/episodes"
#: Append-only JSON-lines file in the bag directory: one episode event per line, written at every flush.
EPISODES_FILE = "episodes.jsonl"
_DIAG_TYPE = topic_spec(EPISODE).msgtype
_COMPRESSION = {None: CompressionType.NONE, "none": CompressionType.NONE,
                "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}

QosLike = QosSpec | Mapping[str, Any] | str | Sequence[QosSpec | Mapping[str, Any]] | None


class BagWriterError(ValueError):
    """Misuse of the bag writer (unknown topic, closed bag, bad argument)."""


_TYPESTORE: Any = None


def jazzy_typestore() -> Any:
    """The shared ``rosbags`` ROS2_JAZZY typestore (message definitions, CDR (de)serialisation)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def _qos_list(qos: QosLike, topic: str) -> list[dict[str, Any]]:
    """Normalise every accepted QoS description to rosbag2's list-of-dicts."""
    if qos is None:
        spec = topic_by_name(topic)
        return [(spec.qos if spec is not None else RELIABLE_VOLATILE).to_rosbag2()]
    if isinstance(qos, str):
        parsed = load_yaml_text(qos, f"QoS of {topic}") if qos.strip() else []
        return _qos_list(parsed or [], topic) if parsed else []
    if isinstance(qos, QosSpec):
        return [qos.to_rosbag2()]
    if isinstance(qos, Mapping):
        return [QosSpec.from_rosbag2(dict(qos)).to_rosbag2() | _extra_keys(qos)]
    out: list[dict[str, Any]] = []
    for item in qos:
        if isinstance(item, QosSpec):
            out.append(item.to_rosbag2())
        elif isinstance(item, Mapping):
            out.append(QosSpec.from_rosbag2(dict(item)).to_rosbag2() | _extra_keys(item))
        else:
            raise BagWriterError(f"offered QoS for {topic!r}: {item!r} is not a QosSpec or a mapping")
    return out


def _extra_keys(d: Mapping[str, Any]) -> dict[str, Any]:
    """Keep the timing fields of a given rosbag2 QoS dict (deadline, lifespan, liveliness...)."""
    keep = ("deadline", "lifespan", "liveliness", "liveliness_lease_duration", "avoid_ros_namespace_conventions")
    return {k: d[k] for k in keep if k in d}


_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # libyaml: ~10x faster, metadata is rewritten often


def _dump_yaml(data: Any) -> str:
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, default_flow_style=False)


def qos_profiles_to_yaml(profiles: QosLike, topic: str = "") -> str:
    """rosbag2's ``offered_qos_profiles`` YAML text for an MCAP channel's metadata."""
    return yaml.safe_dump(_qos_list(profiles, topic), sort_keys=False, default_flow_style=False).strip()


def episode_events_from_diagnostic_array(msg: Any, timestamp_ns: int) -> list[dict[str, Any]]:
    """Episode events in a decoded ``DiagnosticArray`` as summary records (``t_ns`` = log time,
    ``stamp_ns`` = header stamp, ``event``, then the event's values, numbers parsed)."""
    return [{"t_ns": int(timestamp_ns), "event": event, "stamp_ns": stamp, **values}
            for stamp, event, values in parse_episode_events(msg)]


@dataclass
class _Topic:
    name: str
    msgtype: str
    msgdef: str
    rihs01: str
    qos: list[dict[str, Any]]
    qos_yaml: str
    count: int = 0          # messages written (all files)
    flushed: int = 0        # messages known to be on disk
    channel_id: int = -1    # in the current file
    sequence: int = 0


@dataclass
class _File:
    path: Path
    count: int = 0
    start_ns: int = 2**63 - 1
    end_ns: int = 0
    bytes_estimate: int = 0


class BagWriter:
    """Write a rosbag2 MCAP bag from CDR bytes (or ``rosbags`` message objects), without ROS.

    Args:
        path: bag directory to create; must not exist or be an empty directory.
        flush_every_messages: flush (finish the MCAP chunk, flush the file, rewrite
            metadata.yaml) after this many messages; bounds the tail a SIGKILL loses.
        flush_every_seconds: ... or when this much wall time passed since the last flush.
        compression: MCAP chunk compression: None (default), ``"zstd"`` or ``"lz4"``.
        chunk_size: an MCAP chunk is also finished when its buffer exceeds this many bytes.
        max_file_messages / max_file_bytes: start a new ``_k.mcap`` file when the current one
            reaches this many messages / about this many bytes (None = one file).
        custom_data: extra string key/values for metadata.yaml ``custom_data``.
        fsync: also ``os.fsync`` at every flush (survives power loss, not only process kill).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        flush_every_messages: int = 200,
        flush_every_seconds: float = 1.0,
        compression: str | None = None,
        chunk_size: int = 512 * 1024,
        max_file_messages: int | None = None,
        max_file_bytes: int | None = None,
        custom_data: Mapping[str, str] | None = None,
        fsync: bool = False,
    ) -> None:
        if compression not in _COMPRESSION:
            raise BagWriterError(f"compression = {compression!r}, expected None, 'zstd' or 'lz4'")
        if flush_every_messages < 1:
            raise BagWriterError(f"flush_every_messages = {flush_every_messages!r}, expected >= 1")
        if not flush_every_seconds > 0:
            raise BagWriterError(f"flush_every_seconds = {flush_every_seconds!r}, expected > 0")
        for name, lim in (("max_file_messages", max_file_messages), ("max_file_bytes", max_file_bytes)):
            if lim is not None and lim < 1:
                raise BagWriterError(f"{name} = {lim!r}, expected None or >= 1")
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise BagWriterError(f"{self.path} exists and is not an empty directory; not overwriting")
        self.path.mkdir(parents=True, exist_ok=True)
        self.flush_every_messages = int(flush_every_messages)
        self.flush_every_seconds = float(flush_every_seconds)
        self.compression = compression if compression != "none" else None
        self.chunk_size = int(chunk_size)
        self.max_file_messages = max_file_messages
        self.max_file_bytes = max_file_bytes
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.fsync = fsync

        self._topics: dict[str, _Topic] = {}
        self._files: list[_File] = []
        #: episode events not yet in episodes.jsonl; the flushed ones live only there (a long run's memory stays
        #: flat: keeping every event cost ~60 B per decision step)
        self._episodes: list[dict[str, Any]] = []
        self._episodes_flushed = 0
        self._episodes_out: Any = None  # episodes.jsonl, opened at the first event
        self._since_flush = 0
        self._last_flush = time.monotonic()
        self._closed = False
        self._stream: Any = None
        self._mcap: McapFileWriter | None = None
        self._open_file()
        self._write_metadata(finalized=False)

    # ------------------------------------------------------------------ files
    def _open_file(self) -> None:
        index = len(self._files)
        fpath = self.path / f"{self.path.name}_{index}.mcap"
        self._stream = open(fpath, "xb")  # noqa: SIM115 (closed in _close_file)
        self._mcap = McapFileWriter(
            self._stream,
            chunk_size=self.chunk_size,
            compression=_COMPRESSION[self.compression],
            enable_crcs=True,
            enable_data_crcs=True,
        )
        # the finished chunks' indexes wait on disk for the summary: memory stays flat on long runs
        self._chunk_indexes = spill_chunk_indexes(self._mcap, self.path)
        self._mcap.start(profile="ros2", library="der_ros BagWriter (mcap-python)")
        self._files.append(_File(fpath))
        self._schema_ids: dict[str, int] = {}
        for topic in self._topics.values():
            self._register(topic)
        self._mcap.flush()
        self._stream.flush()

    def _register(self, topic: _Topic) -> None:
        assert self._mcap is not None
        sid = self._schema_ids.get(topic.msgtype)
        if sid is None:
            sid = self._mcap.register_schema(topic.msgtype, "ros2msg", topic.msgdef.encode())
            self._schema_ids[topic.msgtype] = sid
        topic.channel_id = self._mcap.register_channel(
            topic.name, "cdr", sid, {"offered_qos_profiles": topic.qos_yaml}
        )

    def _close_file(self) -> None:
        assert self._mcap is not None
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": _dump_yaml(
            self._metadata(finalized=True)["rosbag2_bagfile_information"])})
        events = self.episodes  # read back from episodes.jsonl (flushed before a file is closed): once per file
        if events:
            self._mcap.add_metadata(EPISODES_KEY, {"episodes": json.dumps(events)})
        self._mcap.finish()
        if self._chunk_indexes is not None:
            self._chunk_indexes.close()
        self._stream.flush()
        if self.fsync:
            os.fsync(self._stream.fileno())
        self._stream.close()
        self._mcap = None

    # ------------------------------------------------------------------ topics
    def add_topic(
        self,
        name: str,
        msgtype: str,
        qos: QosLike = None,
        *,
        msgdef: str | None = None,
        rihs01: str | None = None,
    ) -> None:
        """Declare a topic before writing to it.

        ``msgtype`` is ``pkg/msg/Type``. ``qos`` is what the publishers offered: a
        :class:`QosSpec`, a rosbag2 QoS dict, a list of those, or rosbag2 YAML text; None
        takes the QoS of the topic table (``topics.py``) or RELIABLE/VOLATILE depth 10.
        ``msgdef``/``rihs01`` are needed only for types the Jazzy typestore lacks.
        Adding a topic again with the same type is a no-op; with another type an error.
        """
        self._check_open()
        if not name.startswith("/"):
            name = "/" + name
        old = self._topics.get(name)
        if old is not None:
            if old.msgtype != msgtype:
                raise BagWriterError(f"topic {name!r} already has type {old.msgtype!r}, not {msgtype!r}")
            return
        if msgdef is None or rihs01 is None:
            store = jazzy_typestore()
            if msgtype not in store.fielddefs:
                raise BagWriterError(
                    f"message type {msgtype!r} of topic {name!r} is not in the ROS 2 Jazzy typestore; "
                    "pass msgdef= and rihs01="
                )
            msgdef = msgdef if msgdef is not None else store.generate_msgdef(msgtype, ros_version=2)[0]
            rihs01 = rihs01 if rihs01 is not None else store.hash_rihs01(msgtype)
        qos_list = _qos_list(qos, name)
        topic = _Topic(name, msgtype, msgdef, rihs01, qos_list, qos_profiles_to_yaml(qos_list, name))
        self._topics[name] = topic
        self._register(topic)

    def has_topic(self, name: str) -> bool:
        return ("/" + name.lstrip("/")) in self._topics

    @property
    def topics(self) -> dict[str, str]:
        """topic name -> message type."""
        return {t.name: t.msgtype for t in self._topics.values()}

    @property
    def counts(self) -> dict[str, int]:
        """Messages written per topic (including those not yet flushed)."""
        return {t.name: t.count for t in self._topics.values()}

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    @property
    def episodes(self) -> list[dict[str, Any]]:
        """The episode events seen so far (copies): those in episodes.jsonl, then those not flushed yet."""
        flushed = read_episode_summary(self.path) if self._episodes_flushed else []
        return flushed + [dict(e) for e in self._episodes]

    @property
    def files(self) -> list[Path]:
        return [f.path for f in self._files]

    # ------------------------------------------------------------------ writing
    def write(self, topic: str, timestamp_ns: int, data: bytes | bytearray | memoryview,
              *, publish_time_ns: int | None = None) -> None:
        """Append one CDR-serialised message; ``timestamp_ns`` becomes the MCAP log time."""
        self._check_open()
        t = self._topics.get(topic if topic.startswith("/") else "/" + topic)
        if t is None:
            raise BagWriterError(f"topic {topic!r} was not added; call add_topic first")
        ts = int(timestamp_ns)
        if ts < 0:
            raise BagWriterError(f"timestamp_ns = {ts} for {topic!r}, expected >= 0")
        payload = bytes(data)
        assert self._mcap is not None
        self._mcap.add_message(
            channel_id=t.channel_id,
            log_time=ts,
            data=payload,
            publish_time=int(publish_time_ns) if publish_time_ns is not None else ts,
            sequence=t.sequence & 0xFFFFFFFF,
        )
        t.sequence += 1
        t.count += 1
        f = self._files[-1]
        f.count += 1
        f.start_ns = min(f.start_ns, ts)
        f.end_ns = max(f.end_ns, ts)
        f.bytes_estimate += len(payload) + 31
        if t.msgtype == _DIAG_TYPE and t.name.rsplit("/", 1)[-1] == EPISODE:
            self._note_episode(payload, ts)
        self._since_flush += 1
        if (self.max_file_messages is not None and f.count >= self.max_file_messages) or (
            self.max_file_bytes is not None and f.bytes_estimate >= self.max_file_bytes
        ):
            self._rollover()
        elif self._since_flush >= self.flush_every_messages:
            self.flush()
        else:
            self.maybe_flush()

    def write_message(self, topic: str, timestamp_ns: int, msg: Any, *, publish_time_ns: int | None = None) -> None:
        """Serialise a ``rosbags`` typestore message object to CDR and :meth:`write` it."""
        t = self._topics.get(topic if topic.startswith("/") else "/" + topic)
        if t is None:
            raise BagWriterError(f"topic {topic!r} was not added; call add_topic first")
        data = jazzy_typestore().serialize_cdr(msg, t.msgtype)
        self.write(topic, timestamp_ns, data, publish_time_ns=publish_time_ns)

    def mark_episode(
        self,
        timestamp_ns: int,
        *,
        episode: int,
        event: str,
        steps: int = 0,
        ret: float = 0.0,
        lane_changes: int = 0,
        mean_speed: float = 0.0,
        topic: str = EPISODE,
        stamp_ns: int | None = None,
        extra: Mapping[str, Any] | None = None,
        hardware_id: str = "der_ros.bag",
    ) -> None:
        """Write an episode event on ``topic`` exactly as the bridge publishes it.

        ``event`` is one of :data:`EPISODE_EVENTS`. ``stamp_ns`` (header stamp, sim time)
        defaults to ``timestamp_ns``. The event also enters the bag-level episode summary.
        """
        if event not in EPISODE_EVENTS:
            raise BagWriterError(f"mark_episode: event = {event!r}, expected one of {EPISODE_EVENTS}")
        if not self.has_topic(topic):
            self.add_topic(topic, _DIAG_TYPE)
        store = jazzy_typestore()
        diag = store.types
        stamp = int(timestamp_ns if stamp_ns is None else stamp_ns)
        values = episode_values(episode, steps, ret, lane_changes, mean_speed, **(extra or {}))
        status = diag["diagnostic_msgs/msg/DiagnosticStatus"](
            level=1 if event == EPISODE_COLLISION else 0,  # WARN for collisions, as the bridge does
            name=EPISODE_STATUS,
            message=event,
            hardware_id=hardware_id,
            values=[diag["diagnostic_msgs/msg/KeyValue"](key=k, value=format_value(v)) for k, v in values.items()],
        )
        header = diag["std_msgs/msg/Header"](
            stamp=diag["builtin_interfaces/msg/Time"](sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000),
            frame_id="",
        )
        self.write_message(topic, timestamp_ns, diag[_DIAG_TYPE](header=header, status=[status]))

    def _note_episode(self, payload: bytes, ts: int) -> None:
        try:
            msg = jazzy_typestore().deserialize_cdr(payload, _DIAG_TYPE)
        except Exception as exc:  # a corrupt message must not stop recording
            log.warning("could not decode an episode message at %d ns: %s", ts, exc)
            return
        self._episodes.extend(episode_events_from_diagnostic_array(msg, ts))

    # ------------------------------------------------------------------ flushing
    def maybe_flush(self) -> bool:
        """Flush if ``flush_every_seconds`` passed since the last flush and something is pending."""
        if self._closed or self._since_flush == 0:
            return False
        if time.monotonic() - self._last_flush >= self.flush_every_seconds:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Put everything written so far on disk (finished MCAP chunk) and rewrite metadata.yaml."""
        self._check_open()
        assert self._mcap is not None
        self._mcap.flush()
        self._stream.flush()
        if self.fsync:
            os.fsync(self._stream.fileno())
        for t in self._topics.values():
            t.flushed = t.count
        self._flush_episodes()
        self._since_flush = 0
        self._last_flush = time.monotonic()
        self._write_metadata(finalized=False)

    def _flush_episodes(self) -> None:
        """Append the episode events written since the last flush to episodes.jsonl."""
        new = self._episodes
        if new:
            if self._episodes_out is None:
                self._episodes_out = open(self.path / EPISODES_FILE, "a", encoding="utf-8")  # noqa: SIM115
            self._episodes_out.write("".join(json.dumps(e) + "\n" for e in new))
            self._episodes_out.flush()
            if self.fsync:
                os.fsync(self._episodes_out.fileno())
        self._episodes_flushed += len(new)
        self._episodes.clear()

    def _rollover(self) -> None:
        self._flush_episodes()
        self._close_file()
        for t in self._topics.values():
            t.flushed = t.count
        self._since_flush = 0
        self._last_flush = time.monotonic()
        self._open_file()
        self._write_metadata(finalized=False)

    # ------------------------------------------------------------------ metadata
    def _metadata(self, *, finalized: bool) -> dict[str, Any]:
        files = [f for f in self._files if f.count or f is self._files[0]]
        start = min((f.start_ns for f in self._files if f.count), default=0)
        end = max((f.end_ns for f in self._files if f.count), default=0)
        count = sum(t.flushed if not finalized else t.count for t in self._topics.values())
        custom = dict(self.custom_data)
        custom[FINALIZED_KEY] = "true" if finalized else "false"
        custom["der_ros/episode_events"] = str(self._episodes_flushed)
        custom["der_ros/episodes_file"] = EPISODES_FILE
        return {
            "rosbag2_bagfile_information": {
                "version": 9,
                "storage_identifier": "mcap",
                "duration": {"nanoseconds": max(0, end - start)},
                "starting_time": {"nanoseconds_since_epoch": start},
                "message_count": count,
                "topics_with_message_count": [
                    {
                        "topic_metadata": {
                            "name": t.name,
                            "type": t.msgtype,
                            "serialization_format": "cdr",
                            "offered_qos_profiles": t.qos,
                            "type_description_hash": t.rihs01,
                        },
                        "message_count": t.count if finalized else t.flushed,
                    }
                    for t in self._topics.values()
                ],
                "compression_format": "",
                "compression_mode": "",
                "relative_file_paths": [f.path.name for f in files],
                "files": [
                    {
                        "path": f.path.name,
                        "starting_time": {"nanoseconds_since_epoch": f.start_ns if f.count else 0},
                        "duration": {"nanoseconds": max(0, f.end_ns - f.start_ns) if f.count else 0},
                        "message_count": f.count,
                    }
                    for f in files
                ],
                "custom_data": custom,
                "ros_distro": "jazzy",
            }
        }

    def _write_metadata(self, *, finalized: bool) -> None:
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(_dump_yaml(self._metadata(finalized=finalized)))
        tmp.replace(self.path / "metadata.yaml")

    # ------------------------------------------------------------------ lifecycle
    def _check_open(self) -> None:
        if self._closed:
            raise BagWriterError(f"bag {self.path} is closed")

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Finalise: MCAP footer + summary + statistics, final metadata.yaml. Idempotent."""
        if self._closed:
            return
        self._flush_episodes()
        self._close_file()
        if self._episodes_out is not None:
            self._episodes_out.close()
        self._closed = True
        self._write_metadata(finalized=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"BagWriter({str(self.path)!r}, topics={len(self._topics)}, messages={self.message_count})"


def read_episode_summary(bag: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The episode events of a bag directory from its episodes.jsonl (a cut-off last line is ignored)."""
    path = Path(bag) / EPISODES_FILE
    if not path.is_file():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:  # the writer was killed mid-line
            break
    return out


def recover_bag(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> int:
    """Copy a killed (unfinalised) or damaged bag into a new, finalised one; returns the messages copied.

    Our ``ros2 bag reindex``: the messages :class:`~der_ros.bag.reader.BagReader` streams from
    ``src`` -- every complete record up to the cut a kill left, minus any damaged chunk (each
    skipped with a warning) -- are written to ``dst`` with the same topics, message definitions,
    offered QoS, stamps and order. ``src`` is not modified. Works on finalised bags too.
    """
    src = Path(src)
    reader = BagReader(src)
    hashes: dict[str, str] = {}
    custom: dict[str, str] = {}
    for t in (reader.metadata or {}).get("topics_with_message_count") or []:
        tm = t.get("topic_metadata") or {}
        hashes[str(tm.get("name", ""))] = str(tm.get("type_description_hash", "") or "")
    custom = {k: v for k, v in ((reader.metadata or {}).get("custom_data") or {}).items() if not k.startswith("der_ros/")}
    store = jazzy_typestore()
    copied = 0
    with BagWriter(dst, custom_data={**custom, "der_ros/recovered_from": str(src)}) as out:
        for msg in reader.messages():
            conn = msg.connection
            if not out.has_topic(conn.topic):
                own_def = conn.schema if conn.schema and conn.schema_encoding == "ros2msg" else None
                digest = hashes.get(conn.topic) or (store.hash_rihs01(conn.msgtype) if conn.msgtype in store.fielddefs else "")
                out.add_topic(conn.topic, conn.msgtype, conn.metadata.get("offered_qos_profiles", ""),
                              msgdef=own_def, rihs01=digest if own_def is not None else None)
            out.write(conn.topic, msg.log_time, msg.data, publish_time_ns=msg.publish_time)
            copied += 1
    return copied


def add_topics(writer: BagWriter, topics: Iterable[tuple[str, str]]) -> None:
    """Convenience: ``add_topic`` for ``(name, msgtype)`` pairs with the table's QoS."""
    for name, msgtype in topics:
        writer.add_topic(name, msgtype)
