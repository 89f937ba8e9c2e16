"""``agent_node``: the DQN + Double Experience Replay learner as a ROS 2 node (rclpy adapter).

Subscribes to ``state`` (PointCloud2), ``reward`` (Vector3Stamped) and ``episode``
(DiagnosticArray) from the bridge, answers every non-terminal state with a ``lane_change_cmd``
(sensor_msgs/Joy stamped with the state's stamp) and learns online: the stamp join, the
transition rule and the episode accounting live in the ROS-free
:class:`der_ros.agent.online.OnlineLearner`; this module only converts messages, owns the
:class:`der_ros.agent.dqn.DQNAgent` and publishes.

The state, the reward and the command are on the lockstep's round trip, so they are read and written
as CDR bytes (:mod:`der_ros.contract`, :mod:`der_ros.contract`; the graph went from
~0.8x to ~0.89x the in-process loop, ``bench/README.md``); bytes in any other valid encoding are
decoded by rclpy and parsed by the contract, which names what is wrong with a bad message.

The command is published *before* the gradient step of that step runs, so in lockstep the
bridge simulates step k+1 while the agent learns from step k.

Outputs besides the command: ``agent/metrics`` (DiagnosticArray, stable metric names:
``charts/episodic_return``, ``losses/td_loss``, ``replay/h2_size``, ``replay/h2_fraction``,
``replay/h2_weight_mean``, ``online/...`` counters, ``episode/...`` from the bridge's events);
checkpoints to ``checkpoint_out`` every ``checkpoint_every`` learner steps, on the
``agent/save_checkpoint`` service (std_srvs/Trigger) and on SIGINT/SIGTERM (then exit 0).
``agent/set_paused`` (std_srvs/SetBool) switches evaluation mode: greedy actions, no storing,
no learning.

Parameters (:mod:`der_ros.nodes.node_configs`): the node's own (:class:`AgentNodeConfig`, top-level names), ``agent.*``
(:class:`~der_ros.agent.config.DQNConfig`), ``replay.*``
(:class:`~der_ros.replay.config.ReplayConfig`) and ``observation.*``
(:class:`~sumo_bridge.observation.ObservationConfig`, must equal the bridge's
``scenario.observation.*``). ``use_sim_time`` is set in the params YAML (true there).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.clock import Clock as RclClock
from rclpy.clock import ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Joy, PointCloud2
from std_srvs.srv import SetBool, Trigger

from der_ros.agent.divergence import LearnerDiverged, diverged_path
from der_ros.agent.online import OnlineLearner
from der_ros.contract import (
    COMMAND,
    EPISODE,
    EPISODE_START,
    METRICS,
    REWARD,
    STATE,
    cloud_to_points,
    command_cdr,
    header_ns,
    parse_episode_events,
    parse_reward,
    read_reward_cdr,
    read_state_cdr,
)
from der_ros.contract_ros import topic_qos
from der_ros.nodes import msg_conversions as mc
from der_ros.nodes import node_configs
from der_ros.nodes.node_configs import AGENT_MUTABLE, AgentNodeConfig
from der_ros.nodes.params import ConfigParameters
from der_ros.nodes.spin import run_node
from der_ros.train.eval_policies import save_policy
from sumo_bridge.observation import POINT_FIELDS, empty_points, encode_observation

__all__ = ["AgentNode", "parameter_sections", "main"]

_NS = 1_000_000_000


def _deserialize(data: bytes, msg_type: type) -> Any:
    """rclpy's decoding of raw bytes; ValueError (a rejected message) when rclpy cannot decode them."""
    try:
        return deserialize_message(data, msg_type)
    except Exception as exc:  # noqa: BLE001 - whatever rclpy raises for bytes it cannot decode
        raise ValueError(f"undecodable {msg_type.__name__} ({type(exc).__name__}: {exc})") from None


#: learner counters of what it dropped, reported in the log (at most one line per period)
_DROP_COUNTERS = ("stale_state", "stale_reward", "duplicate_state", "duplicate_reward", "gaps", "evicted", "off_grid",
                  "stream_jumps", "abandoned_episodes")
_DROP_LOG_PERIOD = 5.0
#: start-up gate (min_command_subscribers): check period, and consecutive matched checks needed
_READY_CHECK_S = 0.05
_READY_TICKS = 4
#: a stream jump (restarted bridge) is reported sooner
_JUMP_LOG_PERIOD = 1.0


def parameter_sections() -> dict[str, Any]:
    """Prefix -> default config of every parameter section of this node (for YAML tooling)."""
    return node_configs.parameter_sections("agent_node")


class AgentNode(Node):
    """rclpy adapter around OnlineLearner + DQNAgent; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("agent_node")
        import torch  # lazy: torch (and the learner built on it) cost a second to import

        from der_ros.agent.dqn import DQNAgent

        self.finished = False
        #: after SIGINT/SIGTERM, handle the messages already queued for this long before the final save
        self.drain_seconds = 0.3
        self._params = ConfigParameters(self, parameter_sections(), mutable=AGENT_MUTABLE, on_change=self._on_param_change)
        self.cfg: AgentNodeConfig = self._params.get("")
        torch.set_num_threads(self.cfg.torch_threads)
        obs_cfg = self._params.get("observation")
        self._encode = lambda pts: encode_observation(pts, obs_cfg)
        obs_shape = self._encode(empty_points()).shape
        if self.cfg.checkpoint_in:
            self.agent = DQNAgent.load(self.cfg.checkpoint_in, device=self.cfg.device)
            if self.agent.obs_shape != tuple(obs_shape) or self.agent.n_actions != self.cfg.n_actions:
                raise ValueError(
                    f"checkpoint_in {self.cfg.checkpoint_in}: obs_shape {self.agent.obs_shape}, n_actions "
                    f"{self.agent.n_actions}; expected {tuple(obs_shape)}, {self.cfg.n_actions}"
                )
            if not self.agent.parameters_finite():
                raise ValueError(f"checkpoint_in {self.cfg.checkpoint_in}: its weights are not finite (a diverged "
                                 "learner); load an earlier checkpoint")
            self.get_logger().info(
                f"loaded {self.cfg.checkpoint_in} (step {self.agent.steps}); its agent/replay configs replace the "
                "agent.* and replay.* parameters"
            )
        else:
            self.agent = DQNAgent(
                tuple(obs_shape), np.float32, self.cfg.n_actions, self._params.get("agent"),
                self._params.get("replay"), seed=self.cfg.seed, device=self.cfg.device,
            )
        if self.cfg.warm_up:
            self._warm_up(DQNAgent, tuple(obs_shape))
        step_ns = int(round(self.cfg.step_seconds * _NS)) or None
        self.learner = OnlineLearner(self.agent, encode=self._encode, max_buffered=self.cfg.max_buffered,
                                     step_ns=step_ns, max_abs_reward=self.cfg.max_abs_reward)
        self.learner.set_paused(self.cfg.evaluate)
        self.sender_id = f"{self.get_fully_qualified_name()}#{os.getpid()}"
        self.bad_messages: dict[str, int] = {STATE: 0, REWARD: 0, EPISODE: 0}
        #: set when the learner diverged: nothing overwrites checkpoint_out any more; the node stops, exit 1
        self.diverged = False
        self.exit_code = 0
        self._drops_reported = {k: 0 for k in _DROP_COUNTERS}
        self._drops_logged_at = -float("inf")
        self._learn_calls = 0
        self._last_saved_step = self.agent.steps
        self._next_policy_step = self.agent.steps  # the first snapshot: the policy it starts with
        self._maybe_policy()
        self._last_metrics: dict[str, float] = {}
        #: header stamp of the last agent/metrics message: a topic's stamps never go back (issue 45)
        self._metrics_stamp = 0

        self.pub_cmd = self.create_publisher(Joy, COMMAND, topic_qos(COMMAND))
        self.pub_metrics = self.create_publisher(DiagnosticArray, METRICS, topic_qos(METRICS))
        # raw CDR: the state and the reward are read without rclpy's message objects (der_ros/contract/state.py, reward.py)
        self.create_subscription(PointCloud2, STATE, self._on_state, topic_qos(STATE), raw=True)
        self.create_subscription(Vector3Stamped, REWARD, self._on_reward, topic_qos(REWARD), raw=True)
        self.create_subscription(DiagnosticArray, EPISODE, self._on_episode, topic_qos(EPISODE))
        # what is still unreported is logged even when no message follows (steady clock: sim time may stop)
        self.create_timer(_JUMP_LOG_PERIOD, self._report_drops, clock=RclClock(clock_type=ClockType.STEADY_TIME))
        self.create_service(Trigger, "agent/save_checkpoint", self._srv_save)
        self.create_service(SetBool, "agent/set_paused", self._srv_pause)
        self._ready_line = (
            f"agent ready: obs {tuple(obs_shape)}, replay {self.agent.replay_cfg.kind}, "
            f"{'evaluation' if self.learner.paused else 'training'} mode, sender id {self.sender_id}"
        )
        if self.cfg.min_command_subscribers:
            self._matched_ticks = 0
            self._ready_deadline = time.monotonic() + self.cfg.command_wait_timeout
            self._ready_timer = self.create_timer(_READY_CHECK_S, self._maybe_ready,
                                                  clock=RclClock(clock_type=ClockType.STEADY_TIME))  # fmt: skip
        else:
            self.get_logger().info(self._ready_line)

    def _maybe_ready(self) -> None:
        """'agent ready' once the command publisher is matched (a recorder started before us would
        otherwise miss the first commands while its reader is still discovering our writer)."""
        need = self.cfg.min_command_subscribers
        matched = self.pub_cmd.get_subscription_count()
        self._matched_ticks = self._matched_ticks + 1 if matched >= need else 0
        timed_out = time.monotonic() >= self._ready_deadline
        if self._matched_ticks < _READY_TICKS and not timed_out:
            return
        self._ready_timer.cancel()
        if self._matched_ticks < _READY_TICKS:
            self.get_logger().warning(
                f"{COMMAND} has {matched} matched subscription(s) after {self.cfg.command_wait_timeout:g} s, "
                f"expected min_command_subscribers = {need}; starting anyway")
        self.get_logger().info(self._ready_line)

    def _warm_up(self, agent_cls: Any, obs_shape: tuple[int, ...]) -> None:
        """Exercise every lazy path of the learner once, on a throw-away agent with the same configs.

        The first gradient step of a fresh process compiles (or loads from cache) the replay's
        numba kernels and builds torch's autograd state: up to seconds on a loaded machine, during
        which a lockstep bridge would time out and drive the ego with its default action instead of
        the agent's. Running them here, before any subscription exists, keeps that out of the graph
        (the bridge waits for the agent to appear).
        """
        t0 = time.perf_counter()
        batch = self.agent.cfg.batch_size
        dqn_cfg = dataclasses.replace(self.agent.cfg, learning_starts=0)
        replay_cfg = dataclasses.replace(self.agent.replay_cfg, capacity=max(4 * batch, 64))
        scratch = agent_cls(obs_shape, np.float32, self.agent.n_actions, dqn_cfg, replay_cfg, seed=12345,
                            device=self.cfg.device)
        rng = np.random.default_rng(0)
        obs = rng.uniform(-1, 1, size=(3 * batch + 1, *obs_shape)).astype(np.float32)
        for i in range(3 * batch):
            a = scratch.act(obs[i])
            scratch.observe(obs[i], a, float(rng.normal()), obs[i + 1], bool(i % 7 == 6), False)
            scratch.learn()
        self.get_logger().info(f"warm-up done in {time.perf_counter() - t0:.2f}s ({scratch.grad_steps} gradient steps)")

    # -- inputs ----------------------------------------------------------------------------------
    def _reject(self, topic: str, exc: Exception) -> None:
        self.bad_messages[topic] += 1
        self.get_logger().warning(f"rejected {topic} message ({self.bad_messages[topic]} so far): {exc}",
                                  throttle_duration_sec=1.0)

    def _on_state(self, data: bytes) -> None:
        try:  # malformed, non-finite or beyond float32: rejected and counted, never stored
            read = read_state_cdr(data, POINT_FIELDS)  # the bridge's layout, read directly
            if read is None:  # any other encoding: rclpy decodes it, the contract's parser names what is wrong
                msg = _deserialize(data, PointCloud2)
                read = header_ns(msg), cloud_to_points(msg, POINT_FIELDS)
            decisions = self.learner.on_state(*read)
        except ValueError as exc:
            self._reject(STATE, exc)
            return
        self._handle(decisions)

    def _on_reward(self, data: bytes) -> None:
        try:
            r = read_reward_cdr(data)
            if r is None:
                r = parse_reward(_deserialize(data, Vector3Stamped))
            if r.applied_action is not None and not 0 <= r.applied_action < self.cfg.n_actions:
                raise ValueError(f"reward applied_action = {r.applied_action}, expected 0..{self.cfg.n_actions - 1}")
            decisions = self.learner.on_reward(r.stamp_ns, r.reward, r.terminated, r.truncated, r.applied_action)
        except ValueError as exc:
            self._reject(REWARD, exc)
            return
        self._handle(decisions)

    def _report_drops(self) -> None:
        """What the learner dropped (stale, duplicate, evicted, lost steps, stream jumps): one log line at
        most every ``_DROP_LOG_PERIOD`` seconds, with the increments since the last line."""
        counters = self.learner.counters
        if all(counters[k] == self._drops_reported[k] for k in _DROP_COUNTERS):
            return
        now = time.monotonic()
        jumped = counters["stream_jumps"] != self._drops_reported["stream_jumps"]
        if now - self._drops_logged_at < (_JUMP_LOG_PERIOD if jumped else _DROP_LOG_PERIOD):
            return
        new = {k: counters[k] - self._drops_reported[k] for k in _DROP_COUNTERS if counters[k] != self._drops_reported[k]}
        self._drops_reported = {k: counters[k] for k in _DROP_COUNTERS}
        self._drops_logged_at = now
        why = " (the stream jumped: a restarted bridge or a stamp far off; the open transition was dropped)" \
            if jumped else ""
        self.get_logger().warning(
            "dropped since the last report: " + ", ".join(f"{k} +{v}" for k, v in new.items()) + why
            + f"; totals {dict(self._drops_reported)}")

    def _handle(self, decisions: list[Any]) -> None:
        self._report_drops()
        if not decisions:
            return
        for d in decisions:  # answer first: the bridge steps while we learn
            if d.action is not None:
                self.pub_cmd.publish(command_cdr(d.stamp_ns, d.action, self.sender_id))
        for d in decisions:
            if d.stored:
                self._learn()
            if d.episode is not None:
                self._publish_metrics(d.stamp_ns, d.episode.metrics())
        self._maybe_checkpoint()
        self._maybe_policy()

    def _maybe_policy(self) -> None:
        """A policy snapshot at start and every ``policy_every`` steps (der graph evaluates them)."""
        every, steps = self.cfg.policy_every, self.agent.steps
        if every and self.cfg.policy_dir and steps >= self._next_policy_step:
            save_policy(self.cfg.policy_dir, steps, self.agent.q_net)
            self._next_policy_step = (steps // every + 1) * every

    def _learn(self) -> None:
        if self.diverged:
            return
        try:
            metrics = self.learner.learn()
        except LearnerDiverged as exc:
            self._on_diverged(exc)
            return
        if metrics:
            self._last_metrics = metrics
            self._learn_calls += 1
            if self._learn_calls % self.cfg.metrics_every == 0:
                self._publish_metrics(None, {})

    def _on_episode(self, msg: DiagnosticArray) -> None:
        try:
            events = parse_episode_events(msg)
        except ValueError as exc:
            self._reject(EPISODE, exc)
            return
        for stamp, event, values in events:
            if event == EPISODE_START:
                continue
            self.get_logger().info(f"episode {values.get('episode')} ended: {event} {values}")
            metrics = {f"episode/{event}": 1.0}
            for key in ("steps", "return", "lane_changes", "mean_speed"):
                if isinstance(values.get(key), (int, float)):
                    metrics[f"episode/{key}"] = float(values[key])
            self._publish_metrics(stamp, metrics)

    # -- outputs ---------------------------------------------------------------------------------
    def _publish_metrics(self, stamp_ns: int | None, extra: dict[str, float]) -> None:
        metrics: dict[str, float] = {}
        metrics.update(self._last_metrics)
        metrics.update(self.agent.replay.stats())
        metrics.update(self.learner.stats())
        metrics["charts/env_steps"] = float(self.agent.steps)
        metrics["charts/epsilon"] = float(self.agent.epsilon)
        metrics.update({f"agent/bad_{k}": float(v) for k, v in self.bad_messages.items()})
        metrics.update(extra)
        if stamp_ns is None:
            stamp_ns = self.get_clock().now().nanoseconds
        # Metrics are stamped with the step or episode event they follow, or with the clock (sim time:
        # the last /clock received, which runs ahead of an episode event handled later): never earlier
        # than the previous message's stamp, so viewers plotting by header stamp see a monotonic series.
        self._metrics_stamp = max(int(stamp_ns), self._metrics_stamp)
        self.pub_metrics.publish(mc.metrics_to_diagnostics(metrics, self._metrics_stamp, hardware_id=self.sender_id))

    def _maybe_checkpoint(self) -> None:
        every = self.cfg.checkpoint_every
        if every and self.cfg.checkpoint_out and self.agent.steps - self._last_saved_step >= every:
            self.save()

    def save(self) -> Path | None:
        """Write ``checkpoint_out`` (atomic); None when no path is set or the learner diverged.

        A diverged learner (or non-finite weights, however they came) never overwrites
        ``checkpoint_out``: the last good checkpoint stays, the state goes beside it
        (:func:`der_ros.agent.dqn.diverged_path`) once.
        """
        if not self.cfg.checkpoint_out:
            return None
        if not self.diverged and not self.agent.parameters_finite():
            self._on_diverged(LearnerDiverged(f"non-finite weights at env step {self.agent.steps}"))
        if self.diverged:
            return None
        t0 = time.perf_counter()
        path = self.agent.save(self.cfg.checkpoint_out, extra={"online": self.learner.stats()})
        self._last_saved_step = self.agent.steps
        self.get_logger().info(f"saved {path} at step {self.agent.steps} ({time.perf_counter() - t0:.2f}s)")
        return path

    def _on_diverged(self, exc: Exception) -> None:
        """Stop learning and the node (exit 1), keep the last good checkpoint, say so in one line."""
        self.diverged = True
        self.exit_code = 1
        self.finished = True
        out = self.cfg.checkpoint_out
        if not out:
            self.get_logger().error(f"{exc}; no checkpoint_out, nothing saved; stopping")
            return
        kept = f"kept the last good checkpoint {out} (step {self._last_saved_step})" if Path(out).is_file() else \
            f"no good checkpoint was written yet ({out} not created)"
        try:
            bad = self.agent.save(diverged_path(out), extra={"online": self.learner.stats(), "diverged": str(exc)})
            where = f"the state at divergence is in {bad}"
        except OSError as err:
            where = f"the state at divergence could not be written ({err})"
        self.get_logger().error(f"{exc}; {kept}; {where}; stopping")

    def _srv_save(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            path = self.save()
        except OSError as exc:
            response.success, response.message = False, f"saving failed: {exc}"
            return response
        response.success, response.message = save_reply(path, self.cfg.checkpoint_out, self.diverged)
        return response

    def _srv_pause(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        self.learner.set_paused(bool(request.data))
        response.success = True
        response.message = "evaluation mode (no learning)" if self.learner.paused else "training mode"
        self.get_logger().info(response.message)
        return response

    def _on_param_change(self, section: str, cfg: Any, names: list[str]) -> None:
        if section == "":
            self.cfg = cfg
        elif section == "agent" and "agent.lr" in names:
            for group in self.agent.optimizer.param_groups:
                group["lr"] = cfg.lr
            self.agent.cfg.lr = cfg.lr
        elif section == "replay" and "replay.lam" in names:
            self.agent.replay_cfg.lam = cfg.lam
            set_lam = getattr(self.agent.replay, "set_lam", None)
            if callable(set_lam):
                set_lam(cfg.lam)
            elif hasattr(self.agent.replay, "lam"):
                self.agent.replay.lam = cfg.lam
        self.get_logger().info(f"parameters changed: {names}")

    def on_shutdown(self, reason: str) -> None:
        self._publish_metrics(None, {})  # final counters for the recorder / tests
        deadline = time.monotonic() + 0.5
        for pub in (self.pub_cmd, self.pub_metrics):  # let subscribers acknowledge the last messages
            pub.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(), 0.0)))
        try:
            self.save()
        except OSError as exc:
            self.get_logger().error(f"final checkpoint failed: {exc}")
        self.get_logger().info(
            f"stopping ({reason}): {self.agent.steps} env steps, {self.learner.episodes} episodes, "
            f"counters {self.learner.counters}, bad messages {self.bad_messages}"
        )


def save_reply(path: Path | None, checkpoint_out: str, diverged: bool) -> tuple[bool, str]:
    """(success, message) of the save service after :meth:`AgentNode.save` returned ``path``."""
    if path is not None:
        return True, str(path)
    if diverged:
        kept = (f"{checkpoint_out} keeps the last good checkpoint" if Path(checkpoint_out).is_file() else
                f"no good checkpoint was written ({checkpoint_out or 'checkpoint_out is empty'})")
        return False, f"not saved: the learner diverged and a diverged learner is never saved; {kept}"
    return False, "checkpoint_out is empty: nowhere to save"


def main(argv: list[str] | None = None) -> int:
    """Console script ``agent_node`` (ROS arguments: ``--ros-args -p name:=value --params-file f``)."""
    return run_node(AgentNode, argv, executor_kind="events")


if __name__ == "__main__":
    raise SystemExit(main())
