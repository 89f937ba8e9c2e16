"""Record episodes of a SUMO lane-change env into a bag the way the graph records them (ROS-free).

``der graph`` trains in the ROS graph, so its own bag holds training episodes (epsilon-greedy
actions); the episode worth watching at the end is a *greedy* one of the trained agent. This
module runs it in a plain :class:`~sumo_bridge.lane_change_env.LaneChangeEnv` (no graph needed)
and writes what the bridge and agent would have published: the road once, then per step
``reward`` (naming the applied action) and ``state`` stamped t_k = k x step, the scene markers,
the command answering the state, and the ``episode`` start/end events, as the contract's own
bytes (:mod:`der_ros.contract`: the encoders the bridge and the agent publish with), and the
``map -> ego`` transform on ``/tf`` (as the recorder writes it from ``ego/odom``). ``der bag
info/render/export`` read the result like any graph bag.

Times: header stamps are the sim-time step keys t_k, as in the graph; log times are wall-clock
times (the recording's start plus t_k and the order offsets), as a recorder's receive times are,
so viewers show the day the episode was recorded, not 1970.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.bag.writer import BagWriter, jazzy_typestore
from der_ros.contract import (
    COMMAND,
    EPISODE_COLLISION,
    EPISODE_START,
    EPISODE_TIME_LIMIT,
    REWARD,
    SAFETY_EVENTS,
    SAFETY_STATUS,
    SCENE_ROAD,
    SCENE_VEHICLES,
    STATE,
    TF,
    TF_MSGTYPE,
    TF_QOS,
    command_cdr,
    ego_tf_cdr,
    reward_cdr,
    road_markers_cdr,
    state_cdr,
    topic_spec,
    vehicle_markers_cdr,
)
from der_ros.safety.apply import replace_unsafe
from sumo_bridge.observation import POINT_FIELDS, field_index

__all__ = ["RecordedEpisode", "record_episode"]

_NS = 1_000_000_000
#: log-time offsets (ns) of one step's messages: the bridge's order, the agent's answer last
_AT_REWARD, _AT_STATE, _AT_TF, _AT_SCENE, _AT_COMMAND, _AT_END = 1_000, 2_000, 2_500, 3_000, 4_000, 5_000


def _safety_message(ns: int, verdict: str, proposed: int, applied: int, interventions: int) -> Any:
    """``safety/interventions``: one record per command, as the safety node publishes it
    (:func:`der_ros.contract.parse_safety_record` reads it back); WARN level when the command was changed."""
    types = jazzy_typestore().types
    values = [types["diagnostic_msgs/msg/KeyValue"](key=k, value=str(int(v)))
              for k, v in (("proposed", proposed), ("applied", applied), ("interventions", interventions))]  # fmt: skip
    status = types["diagnostic_msgs/msg/DiagnosticStatus"](level=1 if applied != proposed else 0, name=SAFETY_STATUS,
                                                          message=verdict, hardware_id="", values=values)  # fmt: skip
    sec, nanosec = divmod(int(ns), _NS)
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="")
    return types["diagnostic_msgs/msg/DiagnosticArray"](header=header, status=[status])


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
    writer = BagWriter(path, custom_data={"der_ros/recorded_by": "der_ros.offline.episode_recording"})
    try:
        for name in (SCENE_ROAD, REWARD, STATE, SCENE_VEHICLES, COMMAND) + ((SAFETY_EVENTS,) if shield else ()):
            writer.add_topic(name, topic_spec(name).msgtype)
        writer.add_topic(TF, TF_MSGTYPE, TF_QOS)
        vetoes = 0
        obs, info = env.reset(seed=seed)
        t0 = time.time_ns()  # log time of sim time 0 (module docstring)
        writer.write(SCENE_ROAD, t0, road_markers_cdr(env.lanes(), 0, frame_id))
        writer.mark_episode(t0, episode=episode, event=EPISODE_START, stamp_ns=0)
        speed_col = field_index("speed")
        k, ret, lane_changes, lane = 0, 0.0, 0, info.get("lane")
        speed_sum = 0.0
        reward, terminated, truncated, applied = 0.0, False, False, None
        while True:
            t = k * step_ns
            at = t0 + t
            writer.write(REWARD, at + _AT_REWARD, reward_cdr(t, reward, terminated, truncated, applied))
            writer.write(STATE, at + _AT_STATE, state_cdr(info["points"], t, fields=POINT_FIELDS))
            pos = info.get("position")
            if pos is not None:
                writer.write(TF, at + _AT_TF, ego_tf_cdr(t, pos[0], pos[1], float(info.get("angle", 0.0)), frame_id))
            scene = env.scene()
            writer.write(SCENE_VEHICLES, at + _AT_SCENE, vehicle_markers_cdr(scene.vehicles, scene.removed, t, frame_id))
            if terminated or truncated:
                event = info.get("event") or (EPISODE_TIME_LIMIT if truncated else EPISODE_COLLISION)
                writer.mark_episode(at + _AT_END, episode=episode, event=event, steps=k, ret=ret,
                                    lane_changes=lane_changes, mean_speed=speed_sum / max(k, 1), stamp_ns=t)  # fmt: skip
                return RecordedEpisode(Path(path), k, ret, str(event), lane_changes)
            action = int(act(obs))
            if shield is not None:  # as the safety node: proposal in, the command or keep lane out
                proposed = action
                action, vetoed = replace_unsafe(proposed, shield(info["points"]))
                vetoes += vetoed
                writer.write_message(SAFETY_EVENTS, at + _AT_COMMAND, _safety_message(
                    t, "unsafe" if vetoed else "pass", proposed, action, vetoes))  # fmt: skip
            writer.write(COMMAND, at + _AT_COMMAND, command_cdr(t, action, "der_ros.offline.episode_recording"))
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
