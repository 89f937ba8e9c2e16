"""Record episodes of a SUMO lane-change env into a bag the way the graph records them (ROS-free).

``der graph`` trains in the ROS graph, so its own bag holds training episodes (epsilon-greedy
actions); the episode worth watching at the end is a *greedy* one of the trained agent. This
module runs it in a plain :class:`~sumo_bridge.lane_change_env.LaneChangeEnv` (no graph needed)
and writes what the bridge and agent would have published: the road once, then per step
``reward`` (naming the applied action) and ``state`` stamped t_k = k x step, the scene markers,
the command answering the state, and the ``episode`` start/end events
(:mod:`der_ros.contract`). ``der replay info/render/export`` read the result like any graph bag.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.bag.messages import command_message, reward_message, safety_message, state_message
from der_ros.bag.scene_cdr import road_markers_cdr, vehicle_markers_cdr
from der_ros.bag.writer import BagWriter
from der_ros.contract import (
    COMMAND,
    EPISODE_COLLISION,
    EPISODE_START,
    EPISODE_TIME_LIMIT,
    REWARD,
    SAFETY_EVENTS,
    SCENE_ROAD,
    SCENE_VEHICLES,
    STATE,
    topic_spec,
)
from der_ros.safety.apply import replace_unsafe
from sumo_bridge.observation import POINT_FIELDS, field_index

__all__ = ["RecordedEpisode", "record_episode"]

_NS = 1_000_000_000
#: log-time offsets (ns) of one step's messages: the bridge's order, the agent's answer last
_AT_REWARD, _AT_STATE, _AT_SCENE, _AT_COMMAND, _AT_END = 1_000, 2_000, 3_000, 4_000, 5_000


@dataclass(frozen=True)
class RecordedEpisode:
    """What was recorded: the bag directory and the episode's own statistics."""

    path: Path
    steps: int
    ret: float
    outcome: str
    lane_changes: int


def record_episode(env: Any, act: Callable[[np.ndarray], int], path: str | Path, *, seed: int | None,
                   episode: int = 0, frame_id: str = "map",
                   shield: Callable[[np.ndarray], np.ndarray] | None = None) -> RecordedEpisode:  # fmt: skip
    """Run one episode of ``env`` (a LaneChangeEnv, unwrapped) with ``act(observation) -> action``
    from ``reset(seed=seed)`` and write it to a new bag directory ``path``.

    The env's scene is enabled here (position subscriptions from this reset on). ``shield`` (a mask
    of the safe actions from the points, e.g. ``RssChecker.mask``): the command goes through it as
    through the graph's safety node: an unsafe one becomes keep lane, and every command gets its
    ``safety/interventions`` record.
    """
    env.enable_scene()
    step_ns = int(round(float(env.step_seconds) * _NS))
    writer = BagWriter(path, custom_data={"der_ros/recorded_by": "der_ros.bag.episode_recording"})
    try:
        for name in (SCENE_ROAD, REWARD, STATE, SCENE_VEHICLES, COMMAND) + ((SAFETY_EVENTS,) if shield else ()):
            writer.add_topic(name, topic_spec(name).msgtype)
        vetoes = 0
        obs, info = env.reset(seed=seed)
        writer.write(SCENE_ROAD, 0, road_markers_cdr(env.lanes(), 0, frame_id))
        writer.mark_episode(0, episode=episode, event=EPISODE_START, stamp_ns=0)
        speed_col = field_index("speed")
        k, ret, lane_changes, lane = 0, 0.0, 0, info.get("lane")
        speed_sum = 0.0
        reward, terminated, truncated, applied = 0.0, False, False, None
        while True:
            t = k * step_ns
            writer.write_message(REWARD, t + _AT_REWARD, reward_message(t, reward, terminated, truncated, applied))
            writer.write_message(STATE, t + _AT_STATE, state_message(t, info["points"], POINT_FIELDS))
            scene = env.scene()
            writer.write(SCENE_VEHICLES, t + _AT_SCENE, vehicle_markers_cdr(scene.vehicles, scene.removed, t, frame_id))
            if terminated or truncated:
                event = info.get("event") or (EPISODE_TIME_LIMIT if truncated else EPISODE_COLLISION)
                writer.mark_episode(t + _AT_END, episode=episode, event=event, steps=k, ret=ret,
                                    lane_changes=lane_changes, mean_speed=speed_sum / max(k, 1), stamp_ns=t)  # fmt: skip
                return RecordedEpisode(Path(path), k, ret, str(event), lane_changes)
            action = int(act(obs))
            if shield is not None:  # as the safety node: proposal in, the command or keep lane out
                proposed = action
                action, vetoed = replace_unsafe(proposed, shield(info["points"]))
                vetoes += vetoed
                writer.write_message(SAFETY_EVENTS, t + _AT_COMMAND, safety_message(
                    t, "unsafe" if vetoed else "pass", proposed, action, vetoes))  # fmt: skip
            writer.write_message(COMMAND, t + _AT_COMMAND, command_message(t, action, "der_ros.bag.episode_recording"))
            obs, r, terminated, truncated, info = env.step(action)
            reward, applied = float(r), action
            ret += reward
            speed_sum += float(info.get("mean_speed", info["points"][0, speed_col]))
            if info.get("lane") != lane:
                lane_changes += 1
            lane = info.get("lane")
            k += 1
    finally:
        writer.close()
