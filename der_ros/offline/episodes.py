"""Steps and episodes rebuilt from a recorded der_ros bag (ROS-free).

The graph contract (:mod:`der_ros.contract`) keys every decision step by the ``state`` stamp
t_k: ``reward`` (same stamp) carries the reward of arriving in state k, the
terminated/truncated flags and the action the bridge applied in the step that led to k,
``lane_change_cmd`` (same stamp) the action the agent commanded in answer to k, and the
``episode`` topic the bridge's own start/success/collision/time_limit events. The messages
are parsed by the contract's own parsers, the ones the nodes use. Topics are
recorded on different subscriptions, so their log order can interleave; :func:`iter_steps`
joins them by stamp with a bounded reorder window (memory stays flat in the bag length).

Episodes are cut after a step whose reward message says terminated or truncated (the bridge
resets and publishes the new episode's first state at the next stamp). The bridge's end event
of an episode, when recorded, gives its outcome and its own statistics (steps, return,
lane_changes, mean_speed); without it the statistics are computed from the steps and the
outcome is ``terminated`` / ``time_limit`` from the flags (the flags alone cannot tell a success
at the horizon from a time limit), or ``incomplete`` for an episode the bag ends in.
"""

from __future__ import annotations

import heapq
import logging
from array import array
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from der_ros.bag.reader import BagError, BagReader, Message
from der_ros.contract import (
    CLOCK,
    COMMAND,
    EPISODE,
    EPISODE_ENDS,
    EPISODE_START,
    METRICS,
    REWARD,
    SAFETY_EVENTS,
    STATE,
    TOPICS,
    cloud_to_points,
    command_action,
    diagnostics_to_metrics,
    header_ns,
    parse_episode_events,
    parse_reward,
    parse_safety_record,
    point_field_names,
    topic_by_name,
)

__all__ = [
    "ROLE_TYPES",
    "Step",
    "EpisodeSummary",
    "BagScan",
    "resolve_topics",
    "decode_points",
    "iter_steps",
    "scan_bag",
]

log = logging.getLogger(__name__)

#: role (the topic's name in the graph contract) -> message type
ROLE_TYPES: dict[str, str] = {spec.name: spec.msgtype for spec in TOPICS}


def resolve_topics(reader: BagReader, namespace: str | None = None) -> dict[str, str]:
    """role -> bag topic, for the contract topics present in the bag (matched by name and type).

    ``namespace`` (e.g. ``/run1``) picks one graph when a bag holds several; without it the
    first match wins and a warning names the others.
    """
    roles: dict[str, str] = {}
    ns = None if namespace is None else "/" + namespace.strip("/")
    for topic, conn in reader.topics().items():
        spec = topic_by_name(topic)
        if spec is None or spec.msgtype != conn.msgtype:
            continue
        if ns is not None and spec.name != CLOCK and not topic.startswith(ns + "/"):
            continue
        if spec.name in roles:
            log.warning("topics %s and %s both look like %r; using %s (pick one with a namespace)",
                        roles[spec.name], topic, spec.name, roles[spec.name])
            continue
        roles[spec.name] = topic
    return roles


def mistyped_topics(reader: BagReader, roles: Iterable[str] | None = None) -> dict[str, str]:
    """topic -> one sentence, for every topic of the bag named like a contract topic but recorded with another type
    (``/state has type std_msgs/msg/String where sensor_msgs/msg/PointCloud2 was expected``);
    ``roles`` (contract names, e.g. ``STATE``) limits the check to those."""
    wanted = None if roles is None else set(roles)
    found = {}
    for topic, conn in sorted(reader.topics().items()):
        spec = topic_by_name(topic)
        if spec is not None and spec.msgtype != conn.msgtype and (wanted is None or spec.name in wanted):
            found[topic] = f"{topic} has type {conn.msgtype} where {spec.msgtype} was expected"
    return found


def decode_points(msg: Any, where: Message | None = None) -> np.ndarray:
    """A decoded ``state`` PointCloud2 -> ``(n_points, n_fields)`` float64 array, bit-exact
    (:func:`der_ros.contract.cloud_to_points`); :class:`BagError` naming the message if malformed."""
    try:
        return cloud_to_points(msg)
    except ValueError as exc:
        raise _decode_error(where, str(exc)) from None


def _decode_error(where: Message | None, reason: str) -> BagError:
    if where is None:
        return BagError("<message>", None, reason)
    return BagError(where.connection.path, where.offset, reason)


@dataclass
class Step:
    """One decision step t_k, joined by stamp from state / reward / lane_change_cmd."""

    stamp_ns: int
    points: np.ndarray | None = None
    fields: tuple[str, ...] = ()
    reward: float | None = None
    terminated: bool = False
    truncated: bool = False
    #: the action the agent commanded in answer to state k (``lane_change_cmd`` stamped t_k)
    action: int | None = None
    #: the action the bridge applied in the step that led to state k (from the reward stamped t_k;
    #: None at an episode's first state or in bags of bridges that do not report it)
    applied_action: int | None = None


def iter_steps(reader: BagReader, roles: dict[str, str], *, window: int = 256,
               read_all: bool = False, on_message: Callable[[Message], None] | None = None) -> Iterator[Step]:
    """Steps in stamp order, joined from the ``state``, ``reward`` and ``lane_change_cmd`` topics.

    A step is emitted once ``window`` newer stamps have been seen (messages of one step are
    recorded close together) or at the end of the bag. ``on_message(message)`` sees every
    message read, in log order -- every message of the bag with ``read_all`` -- so callers
    collect counts and events in the same pass.
    """
    t_state, t_reward, t_cmd = roles.get(STATE), roles.get(REWARD), roles.get(COMMAND)
    wanted = None if read_all else {t for t in (t_state, t_reward, t_cmd) if t}
    pending: dict[int, Step] = {}
    order: list[int] = []  # heap of the pending stamps
    last_emitted = -1

    def get(stamp: int) -> Step | None:
        if stamp <= last_emitted:
            log.warning("message stamped %d ns arrived after its step was closed; ignoring it", stamp)
            return None
        s = pending.get(stamp)
        if s is None:
            s = pending[stamp] = Step(stamp)
            heapq.heappush(order, stamp)
        return s

    for msg in reader.messages(wanted):
        if on_message is not None:
            on_message(msg)
        topic = msg.topic
        if topic == t_state:
            m = msg.decode()
            s = get(header_ns(m))
            if s is not None:
                s.points = decode_points(m, msg)
                s.fields = point_field_names(m)
        elif topic == t_reward:
            m = msg.decode()
            s = get(header_ns(m))
            if s is not None:
                try:
                    r = parse_reward(m)
                except ValueError as exc:
                    raise _decode_error(msg, str(exc)) from None
                s.reward, s.terminated, s.truncated, s.applied_action = (
                    r.reward, r.terminated, r.truncated, r.applied_action)
        elif topic == t_cmd:
            m = msg.decode()
            s = get(header_ns(m))
            if s is not None:
                try:
                    s.action = command_action(m)
                except ValueError as exc:
                    raise _decode_error(msg, str(exc)) from None
        else:
            continue
        if len(pending) > window:
            k = heapq.heappop(order)
            last_emitted = k
            yield pending.pop(k)
    while order:
        yield pending.pop(heapq.heappop(order))


@dataclass
class EpisodeSummary:
    """One episode of a bag. Statistics come from the bridge's end event when recorded."""

    index: int
    episode: int | None
    start_ns: int
    end_ns: int
    steps: int
    ret: float
    lane_changes: int
    outcome: str
    mean_speed: float
    source: str  # "event" (the bridge's end event) or "steps" (computed from the recorded steps)
    speed_t: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # s since episode start
    speed: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)  # ego speed (m/s)
    #: commands the safety node vetoed in this episode (``safety/interventions``; 0 without a safety node)
    interventions: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "episode": self.episode,
            "start_s": self.start_ns / 1e9,
            "end_s": self.end_ns / 1e9,
            "steps": self.steps,
            "return": self.ret,
            "lane_changes": self.lane_changes,
            "outcome": self.outcome,
            "mean_speed": self.mean_speed,
            "source": self.source,
        }


@dataclass
class BagScan:
    """Everything ``der bag info/plot`` need, from one streamed pass over a bag."""

    name: str
    roles: dict[str, str]
    counts: dict[str, int]
    first_ns: int | None
    last_ns: int | None
    episodes: list[EpisodeSummary]
    events: list[tuple[int, str, dict[str, Any]]]
    metrics: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (stamp seconds, values)
    steps: int
    truncated: bool
    rates: dict[str, dict[int, int]] = field(default_factory=dict)  # topic -> {second since start: count}
    #: stamps of the commands the safety node vetoed (``safety/interventions``; empty without one)
    vetoes: list[int] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) / 1e9


class _Segment:
    """Running statistics of the episode being read (flat memory except the speed trace)."""

    def __init__(self, first: Step) -> None:
        self.start = first.stamp_ns
        self.end = first.stamp_ns
        self.n_steps = 0  # decision steps seen (a state or a reward message at the stamp)
        self.ret = 0.0
        self.lane_changes = 0
        self.last_lane: float | None = None
        self.speed_t = array("d")
        self.speed = array("d")
        self.terminated = False
        self.truncated = False

    def add(self, s: Step, first: bool, i_speed: int | None, i_lane: int | None) -> None:
        self.end = s.stamp_ns
        if s.points is not None or s.reward is not None:
            self.n_steps += 1
        if s.reward is not None and not first:
            self.ret += s.reward
        if s.points is not None:
            ego = s.points[0]
            if i_speed is not None:
                self.speed_t.append((s.stamp_ns - self.start) / 1e9)
                self.speed.append(float(ego[i_speed]))
            if i_lane is not None:
                lane = float(ego[i_lane])
                if self.last_lane is not None and lane != self.last_lane:
                    self.lane_changes += 1
                self.last_lane = lane
        self.terminated = s.terminated
        self.truncated = s.truncated


def scan_bag(reader: BagReader, namespace: str | None = None) -> BagScan:
    """One streamed pass: per-topic counts, time range, steps, episodes, events and metrics."""
    roles = resolve_topics(reader, namespace)
    counts: dict[str, int] = {}
    times = [None, None]
    events: list[tuple[int, str, dict[str, Any]]] = []
    metric_lists: dict[str, tuple[array, array]] = {}
    t_episode, t_metrics, t_safety = roles.get(EPISODE), roles.get(METRICS), roles.get(SAFETY_EVENTS)
    vetoes: list[int] = []

    rates: dict[str, dict[int, int]] = {}

    def on_msg(msg: Message) -> None:
        topic = msg.topic
        counts[topic] = counts.get(topic, 0) + 1
        lt = msg.log_time
        if times[0] is None:
            times[0] = lt
        bins = rates.get(topic)
        if bins is None:
            bins = rates[topic] = {}
        b = (lt - times[0]) // 1_000_000_000
        bins[b] = bins.get(b, 0) + 1
        if lt < times[0]:
            times[0] = lt
        if times[1] is None or lt > times[1]:
            times[1] = lt
        if topic == t_episode:
            events.extend(parse_episode_events(msg.decode()))
        elif topic == t_safety:
            rec = parse_safety_record(msg.decode())
            if rec is not None and rec[3] != rec[2]:  # applied != proposed: a veto
                vetoes.append(rec[0])
        elif topic == t_metrics:
            m = msg.decode()
            t = header_ns(m) / 1e9 if m.header.stamp.sec or m.header.stamp.nanosec else lt / 1e9
            for key, v in diagnostics_to_metrics(m).items():
                ts, vs = metric_lists.setdefault(key, (array("d"), array("d")))
                ts.append(t)
                vs.append(v)

    segments: list[_Segment] = []
    cur: _Segment | None = None
    n_steps = 0
    i_speed = i_lane = None
    for s in iter_steps(reader, roles, read_all=True, on_message=on_msg):
        n_steps += 1
        if s.points is not None and i_speed is None:
            i_speed = s.fields.index("speed") if "speed" in s.fields else None
            i_lane = s.fields.index("lane") if "lane" in s.fields else None
        first = cur is None
        if cur is None:
            cur = _Segment(s)
        cur.add(s, first, i_speed, i_lane)
        if s.terminated or s.truncated:
            segments.append(cur)
            cur = None
    if cur is not None:
        segments.append(cur)

    episodes = _merge(segments, sorted(events, key=lambda e: e[0]))
    if vetoes:
        stamps = np.sort(np.asarray(vetoes, dtype=np.int64))
        for e in episodes:
            e.interventions = int(np.searchsorted(stamps, e.end_ns, "right") - np.searchsorted(stamps, e.start_ns))
    metrics = {k: (np.asarray(ts, dtype=np.float64), np.asarray(vs, dtype=np.float64)) for k, (ts, vs) in metric_lists.items()}
    return BagScan(
        name=reader.name,
        roles=roles,
        counts=counts,
        first_ns=times[0],
        last_ns=times[1],
        episodes=episodes,
        events=events,
        metrics=metrics,
        steps=n_steps,
        truncated=reader.truncated,
        rates=rates,
        vetoes=vetoes,
    )


def _merge(segments: list[_Segment], events: list[tuple[int, str, dict[str, Any]]]) -> list[EpisodeSummary]:
    """Attach the bridge's start/end events to the step segments (or build episodes from events)."""
    out: list[EpisodeSummary] = []
    ends = [e for e in events if e[1] in EPISODE_ENDS]
    starts = [e for e in events if e[1] == EPISODE_START]
    if not segments:
        # Events only (e.g. a bag recorded without state/reward): pair by episode id, else in order.
        start_by_id = {e[2].get("episode"): e for e in starts}
        for i, (st, ev, vals) in enumerate(ends):
            start = start_by_id.get(vals.get("episode"))
            out.append(EpisodeSummary(
                index=i, episode=_int_or_none(vals.get("episode")), start_ns=start[0] if start else st, end_ns=st,
                steps=int(vals.get("steps", 0)), ret=float(vals.get("return", 0.0)),
                lane_changes=int(vals.get("lane_changes", 0)), outcome=ev,
                mean_speed=float(vals.get("mean_speed", float("nan"))), source="event",
            ))
        return out
    bounds = [seg.start for seg in segments] + [2**63]
    for i, seg in enumerate(segments):
        lo, hi = seg.start, bounds[i + 1]
        end = next((e for e in ends if lo <= e[0] < hi), None)
        start = next((e for e in starts if lo <= e[0] < hi), None)
        speed = np.asarray(seg.speed, dtype=np.float64)
        # Like the bridge: the mean over the states reached by a step (the reset state excluded).
        moved = speed[1:] if speed.size > 1 else speed
        computed_speed = float(moved.mean()) if moved.size else float("nan")
        if end is not None:
            st, ev, vals = end
            ep = vals.get("episode", start[2].get("episode") if start else None)
            summary = EpisodeSummary(
                index=i, episode=_int_or_none(ep), start_ns=seg.start, end_ns=seg.end,
                steps=int(vals.get("steps", max(seg.n_steps - 1, 0))),
                ret=float(vals.get("return", seg.ret)),
                lane_changes=int(vals.get("lane_changes", seg.lane_changes)),
                outcome=ev, mean_speed=float(vals.get("mean_speed", computed_speed)), source="event",
            )
        else:
            outcome = "terminated" if seg.terminated else "time_limit" if seg.truncated else "incomplete"
            summary = EpisodeSummary(
                index=i, episode=_int_or_none(start[2].get("episode")) if start else None,
                start_ns=seg.start, end_ns=seg.end, steps=max(seg.n_steps - 1, 0), ret=seg.ret,
                lane_changes=seg.lane_changes, outcome=outcome, mean_speed=computed_speed, source="steps",
            )
        summary.speed_t = np.asarray(seg.speed_t, dtype=np.float64)
        summary.speed = speed
        out.append(summary)
    return out


def _int_or_none(v: Any) -> int | None:
    try:
        return int(v)
    except (TypeError, ValueError):
        return None
