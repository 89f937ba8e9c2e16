"""``bridge_node``: the SUMO lane-change simulation as a ROS 2 node (rclpy adapter).

Owns one :class:`sumo_bridge.lane_change_env.LaneChangeEnv` and speaks the "ROS 2 graph
contract" (:mod:`der_ros.contract`): every step it publishes ``reward``, ``state`` (PointCloud2 of the
points), then ``/clock``, ``ego/odom``, ``scene/vehicles`` (every vehicle as a marker, with ``markers``
on) and, on episode start/end, ``episode``; it applies the actions
arriving on ``lane_change_cmd``. With ``markers`` on it also publishes the road once on the
latched ``scene/road``. The markers come from the env's scene (:mod:`sumo_bridge.scene`), encoded
by :mod:`der_ros.contract` and published as CDR bytes (a tenth of the cost of building rclpy
messages, figures there); they go out after ``state``, while the agent computes its answer.

Step keys: the bridge counts every published state with a global counter k (across episodes,
reset states included) and stamps it t_k = k * step_seconds, so ``/clock`` is monotonic across
episodes and every message of one step shares the stamp t_k.

Modes
-----
``lockstep``
    After publishing step k the bridge waits for the command stamped t_k. The command callback
    steps the simulation directly (single-threaded executor, no polling timer); a one-shot
    steady-clock timer fires after ``command_timeout`` seconds and steps with the default
    action (0 = keep lane). The timeout is a deadline: a command the executor hands over after it
    (before the timer's turn came, e.g. while the scene markers were being published) finds the step
    already timed out. Late and duplicate commands are rejected by
    :class:`sumo_bridge.lockstep.CommandGate` and never applied to another step.
``free_run``
    A timer steps the simulation every ``step_seconds / real_time_factor`` wall seconds with
    the latest valid command received since the previous step (default action if none).

Timers under a flood: the node spins on rclpy's EventsExecutor (``nodes/spin.py``), whose event
queue is FIFO and unbounded; a publisher flooding ``lane_change_cmd`` faster than the events are
handled would delay every timer behind its backlog without bound (the start-up check never ran and
the simulation never began). So the timers' work is also done, when due, at the end of every
command callback (:meth:`BridgeNode._run_overdue`): the start-up check, the free-run tick, and (per
command, see lockstep) the timeout. Without a flood the timers do it, as before.

Bad input never stops the simulation: a rejected command is counted, logged (throttled) and
reported on ``bridge/diagnostics`` (DiagnosticArray, also carrying the round-trip latency
percentiles: state published -> its command received, measured here).

``max_steps`` > 0: after that many simulation steps the node logs a one-line JSON summary
(``bridge summary: {...}``) and exits 0.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock as RclClock
from rclpy.clock import ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2
from visualization_msgs.msg import MarkerArray

from der_ros.contract import (
    BRIDGE_DIAGNOSTICS,
    BRIDGE_STATUS,
    CLOCK,
    COMMAND,
    EPISODE,
    EPISODE_COLLISION,
    EPISODE_ENDS,
    EPISODE_START,
    EPISODE_TIME_LIMIT,
    ODOM,
    REWARD,
    SCENE_ROAD,
    SCENE_VEHICLES,
    STATE,
    cdr_command_sender,
    clock_cdr,
    episode_values,
    odometry_cdr,
    parse_command,
    read_command_cdr,
    reward_cdr,
    road_markers_cdr,
    state_cdr,
    vehicle_markers_cdr,
)
from der_ros.contract_ros import topic_qos
from der_ros.nodes import msg_conversions as mc
from der_ros.nodes import node_configs
from der_ros.nodes.node_configs import BridgeNodeConfig
from der_ros.nodes.params import ConfigParameters
from der_ros.nodes.queue_drain import take_queued
from der_ros.nodes.spin import run_node
from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.lockstep import CommandGate, Verdict
from sumo_bridge.observation import POINT_FIELDS, field_index

__all__ = ["BridgeNode", "LatencyStats", "main", "parameter_sections"]

_NS = 1_000_000_000
#: consecutive timeouts at the start, no command accepted yet, after which the bridge names who publishes and listens
_SILENT_START = 3


class LatencyStats:
    """The last ``capacity`` round-trip times in a ring (numpy), with percentiles in milliseconds.

    The ring is written through once at construction: ``np.zeros`` gets its pages from the kernel
    only as they are first written, so a lazily filled ring grew the bridge's RSS by 8 bytes a step
    until it was full (1.6 MB over 200,000 steps at the old capacity; issue 45, finding 4).
    """

    def __init__(self, capacity: int = 20_000) -> None:
        if capacity < 1:
            raise ValueError(f"capacity = {capacity}, expected >= 1")
        self._buf = np.empty(capacity, dtype=np.int64)
        self._buf.fill(0)  # resident now, not step by step
        self._n = 0

    def add(self, ns: int) -> None:
        self._buf[self._n % len(self._buf)] = ns
        self._n += 1

    def __len__(self) -> int:
        return min(self._n, len(self._buf))

    def percentiles_ms(self) -> dict[str, float]:
        if len(self) == 0:
            return {"roundtrip_p50_ms": float("nan"), "roundtrip_p99_ms": float("nan"), "roundtrip_n": 0.0}
        data = self._buf[: len(self)] / 1e6
        p50, p99 = np.percentile(data, [50, 99])
        return {"roundtrip_p50_ms": float(p50), "roundtrip_p99_ms": float(p99), "roundtrip_n": float(len(self))}


#: seconds between start-up checks (the graph must look ready on 4 consecutive ones)
_STARTUP_CHECK_S = 0.05


def parameter_sections() -> dict[str, Any]:
    """Prefix -> default config of every parameter section of this node (for YAML tooling)."""
    return node_configs.parameter_sections("bridge_node")


class BridgeNode(Node):
    """rclpy adapter: LaneChangeEnv + CommandGate; see the module docstring."""

    def __init__(self, env_factory: Any = None) -> None:
        super().__init__("bridge_node")
        self.finished = False
        self._params = ConfigParameters(self, parameter_sections())
        self.cfg: BridgeNodeConfig = self._params.get("")
        self.scenario = self._params.get("scenario")
        self.env = (env_factory or LaneChangeEnv)(self.scenario)
        self.step_ns = int(round(float(self.env.step_seconds) * _NS))
        self.n_actions = int(getattr(getattr(self.env, "action_space", None), "n", 3))
        self.gate = CommandGate(n_actions=self.n_actions)
        self._speed_col = field_index("speed")

        self.pub_clock = self.create_publisher(Clock, CLOCK, topic_qos(CLOCK))
        self.pub_reward = self.create_publisher(Vector3Stamped, REWARD, topic_qos(REWARD))
        self.pub_state = self.create_publisher(PointCloud2, STATE, topic_qos(STATE))
        self.pub_odom = self.create_publisher(Odometry, ODOM, topic_qos(ODOM))
        self.pub_episode = self.create_publisher(DiagnosticArray, EPISODE, topic_qos(EPISODE))
        self.pub_diag = self.create_publisher(DiagnosticArray, BRIDGE_DIAGNOSTICS, topic_qos(BRIDGE_DIAGNOSTICS))
        # Raw CDR bytes, a deep queue drained in the callback, commands of other senders dropped before they are
        # decoded: a command flood cannot push the agent's answer out of the queue (nodes/queue_drain.py).
        self._cmd_sub = self.create_subscription(Joy, COMMAND, self._on_command,
                                                 topic_qos(COMMAND, depth=self.cfg.command_queue_depth), raw=True)
        self._rejects_logged_at = -float("inf")
        self.pub_vehicles: Publisher | None = None
        if self.cfg.markers:
            self._start_scene()

        steady = RclClock(clock_type=ClockType.STEADY_TIME)
        self._timeout_timer = self.create_timer(self.cfg.command_timeout, self._on_timeout, clock=steady,
                                                autostart=False)
        self._deadline = float("inf")  # time.monotonic() by which the open step's command must be judged (lockstep)
        self._run_timer = None
        self._started = False
        self._next_startup_check = 0.0  # time.monotonic() of the next start-up check
        self._tick_period = float("inf")  # free_run: wall seconds between steps
        self._last_tick = -float("inf")
        self._startup_timer = self.create_timer(_STARTUP_CHECK_S, self._maybe_start, clock=steady)
        self._startup_deadline = time.monotonic() + self.cfg.wait_for_agent
        self._ready_ticks = 0

        self.k = 0  # global count of published states (the step key is k * step_ns)
        self.sim_steps = 0
        self.episode = -1
        self._ep_return = 0.0
        self._ep_steps = 0
        self._ep_lane_changes = 0
        self._ep_speed_sum = 0.0
        self._lane: int | None = None
        self._sent_at: dict[int, int] = {}
        self.latency = LatencyStats()
        self.events: dict[str, int] = dict.fromkeys(EPISODE_ENDS, 0)
        self._t_start = time.perf_counter()
        self._busy_s = 0.0
        self._env_s = 0.0  # of which env.step (the rest: publishing, bookkeeping, episode starts)
        self._publish_s = 0.0  # of which publishing the step (reward, state, clock, odometry, scene)
        self.get_logger().info(
            f"bridge ready: mode={self.cfg.mode} step={self.env.step_seconds}s scenario={self.scenario}"
        )

    # -- scene markers (viewers, recorder) -------------------------------------------------------
    def _start_scene(self) -> None:
        """Per-vehicle position subscriptions in the env, the two marker topics, the road (latched)."""
        self.env.enable_scene()
        self.pub_vehicles = self.create_publisher(MarkerArray, SCENE_VEHICLES, topic_qos(SCENE_VEHICLES))
        self.pub_road = self.create_publisher(MarkerArray, SCENE_ROAD, topic_qos(SCENE_ROAD))
        self.pub_road.publish(road_markers_cdr(self.env.lanes(), 0, self.cfg.map_frame))

    def _publish_scene(self, stamp: int) -> None:
        assert self.pub_vehicles is not None
        scene = self.env.scene()
        self.pub_vehicles.publish(vehicle_markers_cdr(scene.vehicles, scene.removed, stamp, self.cfg.map_frame))

    # -- start-up --------------------------------------------------------------------------------
    def _maybe_start(self) -> None:
        if self._started:
            return
        self._next_startup_check = time.monotonic() + _STARTUP_CHECK_S
        ready = (
            self.count_subscribers(STATE) >= self.cfg.min_subscribers
            and self.count_subscribers(REWARD) >= self.cfg.min_subscribers
            and self.count_publishers(COMMAND) > 0
        )
        # Seen from here, a subscriber is matched as soon as we discovered it; the subscriber may
        # match our writers a moment later, and a first state sent before that would be lost. So
        # the graph must look ready on a few consecutive ticks (0.05 s apart) before step 0.
        self._ready_ticks = self._ready_ticks + 1 if ready else 0
        if self._ready_ticks < 4 and time.monotonic() < self._startup_deadline:
            return
        ready = self._ready_ticks >= 4
        self._started = True
        self._startup_timer.cancel()
        if not ready:
            self.get_logger().warning("no agent found on the graph; starting anyway (default actions on timeout)")
        self._t_start = time.perf_counter()
        self._start_episode()
        if self.cfg.mode == "free_run":
            self._tick_period = self.env.step_seconds / self.cfg.real_time_factor
            self._last_tick = time.monotonic()
            self._run_timer = self.create_timer(self._tick_period, self._on_tick,
                                                clock=RclClock(clock_type=ClockType.STEADY_TIME))  # fmt: skip

    # -- stepping --------------------------------------------------------------------------------
    def _stamp(self) -> int:
        return self.k * self.step_ns

    def _start_episode(self) -> None:
        # The first reset without a seed uses scenario.seed; later resets continue the env's RNG.
        _obs, info = self.env.reset()
        self.episode += 1
        self._ep_return = 0.0
        self._ep_steps = 0
        self._ep_lane_changes = 0
        self._ep_speed_sum = 0.0
        self._lane = info.get("lane")
        stamp = self._stamp()
        self.pub_episode.publish(mc.make_episode_event(stamp, EPISODE_START, episode_values(self.episode, 0, ret=None)))
        self._publish_step(stamp, 0.0, False, False, info, None)

    def _publish_step(
        self, stamp: int, reward: float, terminated: bool, truncated: bool, info: dict, applied: int | None
    ) -> None:
        # CDR bytes (der_ros/contract/): reward and state are on the round trip's critical path, so they go
        # first; /clock, the odometry and the scene follow while the agent computes its answer
        self.pub_reward.publish(reward_cdr(stamp, reward, terminated, truncated, applied))
        if not (terminated or truncated):
            self.gate.open(stamp)  # open before publishing: a fast answer must find the step open
            self._sent_at[stamp] = time.perf_counter_ns()
            if self.cfg.mode == "lockstep":
                self._timeout_timer.reset()
                self._deadline = time.monotonic() + self.cfg.command_timeout
        self.pub_state.publish(state_cdr(info["points"], stamp, fields=POINT_FIELDS))
        self.pub_clock.publish(clock_cdr(stamp))
        pos = info.get("position")
        if pos is not None:
            speed = float(info["points"][0, self._speed_col])
            self.pub_odom.publish(
                odometry_cdr(stamp, pos[0], pos[1], float(info.get("angle", 0.0)), speed, self.cfg.map_frame)
            )
        if self.pub_vehicles is not None:
            self._publish_scene(stamp)

    def _step(self, action: int) -> None:
        t0 = time.perf_counter()
        _obs, reward, terminated, truncated, info = self.env.step(int(action))
        t_env = time.perf_counter()
        self._env_s += t_env - t0
        self.sim_steps += 1
        self.k += 1
        stamp = self._stamp()
        self._ep_return += float(reward)
        self._ep_steps += 1
        self._ep_speed_sum += float(info.get("mean_speed", info["points"][0, self._speed_col]))
        lane = info.get("lane")
        if lane is not None and self._lane is not None and lane != self._lane:
            self._ep_lane_changes += 1
        self._lane = lane
        self._publish_step(stamp, float(reward), bool(terminated), bool(truncated), info, int(action))
        self._publish_s += time.perf_counter() - t_env
        done = self.cfg.max_steps > 0 and self.sim_steps >= self.cfg.max_steps
        if terminated or truncated:
            event = info.get("event") or (EPISODE_TIME_LIMIT if truncated else EPISODE_COLLISION)
            self.events[event] = self.events.get(event, 0) + 1
            cost = {k: float(info[k]) for k in ("imposed_brake", "time_to_success") if info.get(k) is not None}
            values = episode_values(self.episode, self._ep_steps, self._ep_return, self._ep_lane_changes,
                                    self._ep_speed_sum / max(self._ep_steps, 1), **cost)  # traffic mean speed over the episode
            self.pub_episode.publish(mc.make_episode_event(stamp, event, values))
            if not done:
                self.k += 1
                self._start_episode()
        if self.sim_steps % self.cfg.diagnostics_every == 0:
            self._publish_diagnostics()
        self._busy_s += time.perf_counter() - t0
        if done:
            self._finish()

    def _finish(self) -> None:
        self._timeout_timer.cancel()
        if self._run_timer is not None:
            self._run_timer.cancel()
        self.finished = True

    # -- commands --------------------------------------------------------------------------------
    def _on_command(self, data: bytes) -> None:
        # (no MessageInfo: rclpy 7.1's has no publisher GID, the sender id is header.frame_id)
        self._judge_command(data)
        for queued in take_queued(self._cmd_sub, self.cfg.command_queue_depth):  # the rest of the queue, now
            self._judge_command(queued)
        self._run_overdue()

    def _run_overdue(self) -> None:
        """The timers' work that is due now: a command flood can delay the timers themselves (module docstring)."""
        if self.finished:
            return
        now = time.monotonic()
        if not self._started:
            if now >= self._next_startup_check:
                self._maybe_start()
        elif self.cfg.mode == "free_run" and now >= self._last_tick + self._tick_period:
            self._on_tick()

    def _judge_command(self, data: bytes) -> None:
        if self.finished:
            return
        # Checked for every command, the drained ones too (a step opened while this callback ran has its own
        # deadline): once the open step's deadline has passed, it times out before the timer's turn, and a
        # command for it is late.
        if self.cfg.mode == "lockstep" and self.gate.open_key is not None and time.monotonic() >= self._deadline:
            self._on_timeout()
            if self.finished:
                return
        sender = cdr_command_sender(data)
        early = self.gate.screen(sender)  # not the locked sender: dropped undecoded (a few us, not ~50)
        if early is not None:
            self._log_reject(early, f"sender={sender!r}")
            return
        command = read_command_cdr(data)  # little-endian plain CDR read directly (der_ros/contract/command.py)
        if command is None:  # another encoding: rclpy decodes it
            try:
                command = parse_command(deserialize_message(data, Joy))
            except Exception as exc:  # noqa: BLE001 - bytes rclpy cannot decode are a malformed command
                self.gate.screen(None)
                self._log_reject(Verdict.MALFORMED, f"undecodable ({type(exc).__name__})")
                return
        stamp, buttons, axes, sender = command
        verdict, action = self.gate.offer(stamp, buttons, axes, sender)
        if verdict is not Verdict.ACCEPTED:
            self._log_reject(verdict, f"stamp={stamp} buttons={buttons} axes={axes} sender={sender!r}")
            return
        sent = self._sent_at.pop(stamp, None)
        if sent is not None:
            self.latency.add(time.perf_counter_ns() - sent)
        if self.cfg.mode == "lockstep":
            self._timeout_timer.cancel()
            self._step(action)

    def _log_reject(self, verdict: Verdict, what: str) -> None:
        """Every rejection is counted by the gate; the log gets one line a second at most, built only then."""
        now = time.monotonic()
        if now - self._rejects_logged_at >= 1.0:
            self._rejects_logged_at = now
            self.get_logger().warning(f"rejected lane_change_cmd ({verdict.value}): {what}; counters={self.gate.stats()}")

    def _on_timeout(self) -> None:
        self._timeout_timer.cancel()
        if self.finished or self.gate.open_key is None:
            return
        key = self.gate.open_key
        self._sent_at.pop(key, None)
        action = self.gate.expire()
        self.get_logger().warning(
            f"no command for step stamped {key} within {self.cfg.command_timeout}s: default action {action}",
            throttle_duration_sec=1.0,
        )
        if self.gate.counters["timeouts"] == _SILENT_START and not self.gate.counters["accepted"]:
            # the agent has answered nothing yet: name who publishes commands and who listens (diagnosis of a
            # deaf or absent agent; der graph fails a run the agent never answered)
            pubs = [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in self.get_publishers_info_by_topic(COMMAND)]
            subs = [f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in self.get_subscriptions_info_by_topic(STATE)]
            self.get_logger().warning(
                f"no answer to any of the first {_SILENT_START} states: {COMMAND} publishers {pubs}, {STATE} "
                f"subscribers {subs}, command counters {self.gate.stats()}")
        self._step(action)

    def _on_tick(self) -> None:
        if self.finished:
            return
        now = time.monotonic()
        if now < self._last_tick + 0.5 * self._tick_period:  # stepped from the command path a moment ago
            return
        self._last_tick = now
        if self.gate.open_key is not None:
            self._sent_at.pop(self.gate.open_key, None)
        self._step(self.gate.take_latest())

    # -- reporting -------------------------------------------------------------------------------
    def summary(self) -> dict[str, float]:
        """Counters, events, throughput and round-trip percentiles (also the exit log line)."""
        wall = max(time.perf_counter() - self._t_start, 1e-9)
        out: dict[str, float] = {
            "sim_steps": float(self.sim_steps),
            "published_states": float(self.k + 1),
            "episodes_started": float(self.episode + 1),
            "steps_per_s": self.sim_steps / wall,
            "busy_fraction": self._busy_s / wall,
            "env_step_fraction": self._env_s / wall,
            "publish_fraction": self._publish_s / wall,
        }
        out.update({f"events/{k}": float(v) for k, v in self.events.items()})
        out.update({f"commands/{k}": float(v) for k, v in self.gate.stats().items()})
        out.update(self.latency.percentiles_ms())
        return out

    def _publish_diagnostics(self) -> None:
        stats = self.gate.stats()
        rejected = any(stats[v.value] for v in Verdict if v is not Verdict.ACCEPTED)
        self.pub_diag.publish(mc.make_diagnostics(self._stamp(), BRIDGE_STATUS, self.summary(), message=self.cfg.mode,
                                                  hardware_id="sumo", warn=rejected))

    def on_shutdown(self, reason: str) -> None:
        self._publish_diagnostics()
        # Exiting right after the last publish could drop the final state / episode event for a
        # subscriber still receiving it: give the reliable writers a bounded moment to get their acks
        # (acks follow Fast DDS heartbeats, so this often runs to the deadline; the data itself is
        # usually delivered long before).
        deadline = time.monotonic() + 0.5
        for pub in (self.pub_reward, self.pub_state, self.pub_episode, self.pub_diag, self.pub_vehicles):
            if pub is None:
                continue
            if not pub.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(), 0.0))):
                self.get_logger().debug(f"{pub.topic_name}: not every subscriber acknowledged the last messages")
        summary = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in self.summary().items()}
        self.get_logger().info(f"stopping ({reason}); bridge summary: {json.dumps(summary, sort_keys=True)}")
        try:
            self.env.close()
        except Exception as exc:  # closing SUMO must not hide the summary
            self.get_logger().warning(f"env.close() failed: {exc}")


def main(argv: list[str] | None = None) -> int:
    """Console script ``bridge_node`` (ROS arguments: ``--ros-args -p name:=value --params-file f``)."""
    return run_node(BridgeNode, argv, executor_kind="events")


if __name__ == "__main__":
    raise SystemExit(main())

