"""The recorded scene of chosen episodes, step by step, from a der_ros bag (ROS-free).

What ``der bag render`` draws: the road (``scene/road``), and for every decision step of the
chosen episodes the vehicles as they were (``scene/vehicles``, markers applied in order: ADD
moves or adds, DELETE removes, DELETEALL clears), joined by the step key t_k with the reward of
arriving there and the action taken from there (``reward`` and ``lane_change_cmd``, parsed by
:mod:`der_ros.contract`). Episodes come from :func:`der_ros.offline.episodes.scan_bag`, so they are
numbered as ``der bag info`` shows them.

The bridge puts every vehicle into every ``scene/vehicles`` message (plus a DELETE for each one
gone), so the scene of a step needs no message before its episode: messages stamped before the
chosen episodes are skipped without decoding (their stamp read from the CDR header,
:func:`der_ros.contract.first_stamp_ns`), which keeps rendering one episode of a long urban
bag (~220 markers a step) from decoding all of them.

A bag recorded without markers (bridge ``markers:=false`` or recorder ``record_scene:=false``)
has nothing to draw: :class:`~der_ros.bag.reader.BagError` says so and how to record one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from der_ros.bag.reader import BagError, BagReader
from der_ros.contract import (
    COMMAND,
    EGO_ROLE,
    REWARD,
    SAFETY_EVENTS,
    SCENE_ROAD,
    SCENE_VEHICLES,
    LaneLine,
    VehicleMarker,
    command_action,
    first_stamp_ns,
    header_ns,
    parse_reward,
    parse_road_markers,
    parse_safety_record,
    parse_vehicle_markers,
)
from der_ros.offline.episodes import EpisodeSummary, resolve_topics, scan_bag

__all__ = ["Frame", "EpisodeFrames", "SceneRecording", "select_episodes", "read_scene"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Frame:
    """The scene at one decision step of an episode."""

    stamp_ns: int
    #: decision step within the episode (0: the state the episode starts in)
    step: int
    vehicles: tuple[VehicleMarker, ...]
    #: the reward of arriving here (None at step 0 or when not recorded)
    reward: float | None
    #: the sum of the rewards up to here
    ret: float
    #: the action taken from here: the one the bridge applied (named by the next reward), else the
    #: agent's command; None at the episode's last step
    action: int | None
    #: the command the safety node vetoed at this step (``safety/interventions``; keep lane was applied
    #: instead), None when it let the command through or no safety node was recorded
    vetoed: int | None = None

    def ego(self) -> VehicleMarker | None:
        return next((v for v in self.vehicles if v.role == EGO_ROLE), None)


@dataclass
class EpisodeFrames:
    """One episode's frames, with the numbers ``der bag info`` shows for it."""

    summary: EpisodeSummary
    frames: list[Frame] = field(default_factory=list)

    @property
    def label(self) -> str:
        """The episode's number as the bridge counted it (else its index in the bag)."""
        return str(self.summary.episode if self.summary.episode is not None else self.summary.index)


@dataclass
class SceneRecording:
    """The road and the chosen episodes of a bag."""

    lanes: list[LaneLine]
    episodes: list[EpisodeFrames]
    #: seconds between decision steps (from the step keys; 0.5 if a bag has a single step)
    step_seconds: float

    @property
    def n_frames(self) -> int:
        return sum(len(e.frames) for e in self.episodes)


def _number(e: EpisodeSummary) -> int:
    return e.episode if e.episode is not None else e.index


def select_episodes(episodes: list[EpisodeSummary], episode: int | None = None,
                    span: tuple[int, int] | None = None, where: str = "bag") -> list[EpisodeSummary]:  # fmt: skip
    """The episodes numbered ``episode`` or within ``span`` (inclusive), by the bridge's episode
    number (its index in the bag when the bag has no episode events); neither: the last finished
    episode. ValueError naming what exists when nothing matches."""
    if not episodes:
        raise ValueError(f"{where} has no episodes (no state/reward/episode messages of the der_ros graph)")
    numbers = [_number(e) for e in episodes]
    have = f"episodes {min(numbers)}-{max(numbers)}" if len(numbers) > 1 else f"episode {numbers[0]}"
    if episode is not None:
        chosen = [e for e in episodes if _number(e) == episode]
        if not chosen:
            raise ValueError(f"{where} has no episode {episode} ({have})")
        return chosen[:1]
    if span is not None:
        lo, hi = span
        if lo > hi:
            raise ValueError(f"--episodes {lo}-{hi}: the first episode is after the last")
        chosen = [e for e in episodes if lo <= _number(e) <= hi]
        if not chosen:
            raise ValueError(f"{where} has no episode in {lo}-{hi} ({have})")
        return chosen
    finished = [e for e in episodes if e.outcome != "incomplete"]
    return [(finished or episodes)[-1]]


def read_scene(reader: BagReader, episode: int | None = None, span: tuple[int, int] | None = None,
               namespace: str | None = None) -> SceneRecording:  # fmt: skip
    """The road and the frames of the chosen episodes (see :func:`select_episodes`)."""
    roles = resolve_topics(reader, namespace)
    t_vehicles, t_road = roles.get(SCENE_VEHICLES), roles.get(SCENE_ROAD)
    if t_vehicles is None:
        raise BagError(reader.path, None, f"no {SCENE_VEHICLES} markers in this bag (it was recorded with the scene off: "
                       "bridge_node markers:=false or recorder_node record_scene:=false); record with both on (the "
                       "defaults) to render episodes")  # fmt: skip
    try:
        chosen = select_episodes(scan_bag(reader, namespace).episodes, episode, span, where="the bag")
    except ValueError as exc:
        raise BagError(reader.path, None, str(exc)) from None
    ranges = [(e.start_ns, e.end_ns) for e in chosen]
    first_start = min(lo for lo, _ in ranges)

    def wanted(stamp: int) -> bool:
        return any(lo <= stamp <= hi for lo, hi in ranges)

    lanes: list[LaneLine] = []
    current: dict[int, VehicleMarker] = {}
    snapshots: dict[int, tuple[VehicleMarker, ...]] = {}
    rewards: dict[int, tuple[float, int | None]] = {}
    commands: dict[int, int] = {}
    vetoes: dict[int, int] = {}
    t_reward, t_cmd, t_safety = roles.get(REWARD), roles.get(COMMAND), roles.get(SAFETY_EVENTS)
    topics = {t for t in (t_vehicles, t_road, t_reward, t_cmd, t_safety) if t}
    for msg in reader.messages(topics):
        topic = msg.topic
        try:
            if topic == t_vehicles:
                first = first_stamp_ns(msg.data)
                if first is not None and first < first_start:
                    continue
                update = parse_vehicle_markers(msg.decode())
                if update.delete_all:
                    current.clear()
                for marker_id in update.deleted:
                    current.pop(marker_id, None)
                for v in update.vehicles:
                    current[v.marker_id] = v
                if wanted(update.stamp_ns):
                    snapshots[update.stamp_ns] = tuple(current.values())
            elif topic == t_road:
                lanes = parse_road_markers(msg.decode())
            elif topic == t_reward:
                r = parse_reward(msg.decode())
                if wanted(r.stamp_ns):
                    rewards[r.stamp_ns] = (r.reward, r.applied_action)
            elif topic == t_cmd:
                m = msg.decode()
                if wanted(header_ns(m)):
                    commands[header_ns(m)] = command_action(m)
            elif topic == t_safety:
                rec = parse_safety_record(msg.decode())
                if rec is not None and wanted(rec[0]) and rec[3] != rec[2]:  # applied != proposed: a veto
                    vetoes[rec[0]] = rec[2]
        except ValueError as exc:
            raise BagError(msg.connection.path, msg.offset, f"{topic}: {exc}") from None
    if t_road is None or not lanes:
        log.warning("%s: no %s markers; drawing the vehicles without the road", reader.path, SCENE_ROAD)
    out = []
    all_stamps = sorted(snapshots)
    for e in chosen:
        stamps = [s for s in all_stamps if e.start_ns <= s <= e.end_ns]
        ep = EpisodeFrames(e)
        ret = 0.0
        for i, stamp in enumerate(stamps):
            reward = rewards.get(stamp, (None, None))[0] if i > 0 else None
            ret += reward or 0.0
            action = None
            if i + 1 < len(stamps):
                applied = rewards.get(stamps[i + 1], (None, None))[1]
                action = applied if applied is not None else commands.get(stamp)
            ep.frames.append(Frame(stamp, i, snapshots[stamp], reward, ret, action, vetoes.get(stamp)))
        out.append(ep)
    gaps = [b - a for a, b in zip(all_stamps, all_stamps[1:]) if b > a]
    step_seconds = min(gaps) / 1e9 if gaps else 0.5
    return SceneRecording(lanes, out, step_seconds)
