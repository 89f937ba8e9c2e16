"""ROS-free core of the agent node: join ``state`` and ``reward`` by stamp, form transitions, act.

The bridge publishes, for every step key t_k (nanoseconds of sim time), a ``reward`` message
(reward received on arriving in state k, terminated, truncated) and a ``state`` message. DDS
orders messages within a topic but not across topics, so :class:`OnlineLearner` buffers both
halves by stamp and processes a step once both are present ("completed"), in stamp order.

Transitions follow the graph contract of docs/architecture.md::

    (s_k, a_k, r_{k+1}, s_{k+1}, terminated_{k+1}, truncated_{k+1})

where a_k is the action this learner answered state k with, and the reward and flags come from
the message stamped t_{k+1}. After a terminal step (terminated or truncated) no action is sent
(the bridge resets and publishes the next episode's first state at the next stamp), and the
next completed step starts a new episode (its reward, 0 by contract, is not part of any
transition or return).

Robustness (all counted in :attr:`OnlineLearner.counters`):

* a second message of a topic for a stamp already buffered -> ``duplicate_state`` /
  ``duplicate_reward``, ignored;
* a message for a stamp at or before the last completed step -> ``stale_state`` /
  ``stale_reward``, ignored (never forms a transition out of order);
* when step t completes while an earlier step (after the pending one) is still incomplete, that
  earlier step is lost: ``gaps`` += 1, the incomplete halves are dropped and the pending
  (s, a) is discarded instead of being joined to the wrong next state;
* with ``step_ns`` known (stamps are t_k = k * step_ns), a step lost on *both* topics is a gap
  too (without it such a loss cannot be told from normal succession);
* the bridge reports in each reward which action it applied (``applied_action``); when that is
  not the action this learner sent (the command missed the bridge's timeout and the default was
  applied), the transition stores the applied one: ``overridden_actions``;
* at most ``max_buffered`` incomplete stamps are kept; the oldest is evicted (``evicted``).

Paused (evaluation mode): act greedily (``explore=False``), store nothing and never learn;
episode accounting continues (reported with ``eval/`` metric names).

The node publishes the action first and calls :meth:`OnlineLearner.learn` afterwards, so the
gradient step overlaps with the simulation step in the bridge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

__all__ = ["AgentLike", "Decision", "EpisodeSummary", "OnlineLearner"]


class AgentLike(Protocol):
    """The part of :class:`der_ros.agent.dqn.DQNAgent` the online learner drives."""

    def act(self, obs: np.ndarray, explore: bool = True) -> int: ...

    def observe(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool, truncated: bool
    ) -> None: ...

    def learn(self) -> dict[str, float]: ...


@dataclass
class EpisodeSummary:
    """One finished episode as seen by the agent."""

    index: int
    ret: float
    length: int
    lane_change_cmds: int
    terminated: bool
    truncated: bool
    evaluation: bool
    end_stamp_ns: int

    def metrics(self) -> dict[str, float]:
        """Stable metric names (``charts/`` while training, ``eval/`` in evaluation mode)."""
        p = "eval" if self.evaluation else "charts"
        return {
            f"{p}/episodic_return": self.ret,
            f"{p}/episodic_length": float(self.length),
            f"{p}/lane_change_cmds": float(self.lane_change_cmds),
            f"{p}/episodes": float(self.index + 1),
        }


@dataclass
class Decision:
    """What the node must do after a step completed."""

    stamp_ns: int
    #: action answering the state stamped ``stamp_ns``; None at terminal states (send nothing)
    action: int | None
    #: set when this step ended an episode
    episode: EpisodeSummary | None = None
    #: True when a transition was stored (learn() may be due)
    stored: bool = False


@dataclass
class _Half:
    obs: np.ndarray | None = None
    reward: tuple[float, bool, bool, int | None] | None = None


@dataclass
class _Episode:
    ret: float = 0.0
    length: int = 0
    lane_change_cmds: int = 0
    evaluation: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


class OnlineLearner:
    """Joins ``state``/``reward`` messages by stamp and drives a DQN agent one step at a time.

    ``encode`` turns a state payload (the decoded points) into the observation the agent sees;
    the identity by default. ``keep_lane_action`` is the action not counted as a lane-change
    command. ``step_ns`` (optional) is the bridge's step in nanoseconds, to detect whole lost steps.
    """

    def __init__(
        self,
        agent: AgentLike,
        encode: Callable[[np.ndarray], np.ndarray] | None = None,
        max_buffered: int = 64,
        keep_lane_action: int = 0,
        step_ns: int | None = None,
    ) -> None:
        if max_buffered < 1:
            raise ValueError(f"max_buffered = {max_buffered}, expected >= 1")
        self.agent = agent
        self.encode = encode if encode is not None else (lambda x: x)
        self.max_buffered = max_buffered
        self.keep_lane_action = keep_lane_action
        self.step_ns = step_ns if step_ns else None
        self.paused = False
        self._buf: dict[int, _Half] = {}
        self._last_completed: int | None = None
        self._pending: tuple[np.ndarray, int, int] | None = None  # (obs_k, a_k, t_k)
        self._episode: _Episode | None = None
        self.episodes = 0
        self.env_steps = 0  # completed steps (states acted on or terminal)
        self.last_learn_metrics: dict[str, float] = {}
        self.counters: dict[str, int] = {
            name: 0
            for name in (
                "states",
                "rewards",
                "duplicate_state",
                "duplicate_reward",
                "stale_state",
                "stale_reward",
                "gaps",
                "evicted",
                "transitions",
                "actions",
                "learn_steps",
                "overridden_actions",
            )
        }

    # -- inputs ----------------------------------------------------------------------------------
    def on_state(self, stamp_ns: int, payload: np.ndarray) -> list[Decision]:
        """A ``state`` message arrived; returns the decisions of every step it completed."""
        self.counters["states"] += 1
        if self._is_stale(stamp_ns):
            self.counters["stale_state"] += 1
            return []
        half = self._slot(stamp_ns)
        if half.obs is not None:
            self.counters["duplicate_state"] += 1
            return []
        half.obs = np.asarray(self.encode(payload))
        return self._drain()

    def on_reward(
        self, stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None
    ) -> list[Decision]:
        """A ``reward`` message arrived; returns the decisions of every step it completed.

        ``applied_action`` is the action the bridge reports it applied in the step that led to
        this state (None if it does not say); it replaces this learner's own action in the
        transition when they differ (a command that missed the bridge's timeout).
        """
        self.counters["rewards"] += 1
        if self._is_stale(stamp_ns):
            self.counters["stale_reward"] += 1
            return []
        half = self._slot(stamp_ns)
        if half.reward is not None:
            self.counters["duplicate_reward"] += 1
            return []
        half.reward = (float(reward), bool(terminated), bool(truncated), applied_action)
        return self._drain()

    def set_paused(self, paused: bool) -> None:
        """Evaluation mode on/off. The current pending step is dropped so that no transition mixes
        a greedy evaluation action with training."""
        if paused != self.paused:
            self.paused = paused
            self._pending = None

    def learn(self) -> dict[str, float]:
        """One call of ``agent.learn()`` unless paused; returns its metrics ({} when none were due)."""
        if self.paused:
            return {}
        metrics = self.agent.learn()
        if metrics:
            self.counters["learn_steps"] += 1
            self.last_learn_metrics = dict(metrics)
        return metrics

    # -- state -----------------------------------------------------------------------------------
    @property
    def pending_stamp(self) -> int | None:
        """Stamp of the state waiting for its successor (None between episodes)."""
        return None if self._pending is None else self._pending[2]

    @property
    def buffered(self) -> int:
        """Incomplete stamps held."""
        return len(self._buf)

    def stats(self) -> dict[str, float]:
        """Counters under stable ``online/`` names."""
        out = {f"online/{k}": float(v) for k, v in self.counters.items()}
        out["online/buffered"] = float(len(self._buf))
        out["online/paused"] = 1.0 if self.paused else 0.0
        return out

    # -- internals -------------------------------------------------------------------------------
    def _is_stale(self, stamp_ns: int) -> bool:
        return self._last_completed is not None and stamp_ns <= self._last_completed

    def _slot(self, stamp_ns: int) -> _Half:
        half = self._buf.get(stamp_ns)
        if half is None:
            if len(self._buf) >= self.max_buffered:
                oldest = min(self._buf)
                del self._buf[oldest]
                self.counters["evicted"] += 1
            half = self._buf[stamp_ns] = _Half()
        return half

    def _drain(self) -> list[Decision]:
        """Process every complete stamp, oldest first; earlier incomplete stamps count as gaps."""
        out: list[Decision] = []
        while True:
            complete = [t for t, h in self._buf.items() if h.obs is not None and h.reward is not None]
            if not complete:
                return out
            t = min(complete)
            earlier = [s for s in self._buf if s < t]
            if earlier:
                for s in earlier:
                    del self._buf[s]
                self.counters["gaps"] += 1
                self._pending = None  # its successor was lost: never join it to a later state
            half = self._buf.pop(t)
            out.append(self._complete(t, half.obs, *half.reward))

    def _complete(
        self, t: int, obs: np.ndarray, reward: float, terminated: bool, truncated: bool, applied: int | None
    ) -> Decision:
        self._last_completed = t
        self.env_steps += 1
        stored = False
        if self._pending is not None and self.step_ns is not None and t - self._pending[2] != self.step_ns:
            self.counters["gaps"] += 1  # a whole step (both topics) was lost
            self._pending = None
        if self._pending is not None:
            prev_obs, prev_action, _ = self._pending
            if applied is not None and applied != prev_action:
                self.counters["overridden_actions"] += 1  # the bridge applied its default instead
                prev_action = applied
            ep = self._episode
            assert ep is not None
            ep.ret += reward
            ep.length += 1
            if not self.paused:
                self.agent.observe(prev_obs, prev_action, reward, obs, terminated, truncated)
                self.counters["transitions"] += 1
                stored = True
        else:
            # First state of an episode (or the first after a gap / a pause toggle).
            if self._episode is None:
                self._episode = _Episode(evaluation=self.paused)
        if terminated or truncated:
            summary = self._finish(t, terminated, truncated)
            self._pending = None
            return Decision(stamp_ns=t, action=None, episode=summary, stored=stored)
        action = int(self.agent.act(obs, explore=not self.paused))
        self.counters["actions"] += 1
        if action != self.keep_lane_action and self._episode is not None:
            self._episode.lane_change_cmds += 1
        self._pending = (obs, action, t)
        return Decision(stamp_ns=t, action=action, stored=stored)

    def _finish(self, t: int, terminated: bool, truncated: bool) -> EpisodeSummary:
        ep = self._episode or _Episode(evaluation=self.paused)
        summary = EpisodeSummary(
            index=self.episodes,
            ret=ep.ret,
            length=ep.length,
            lane_change_cmds=ep.lane_change_cmds,
            terminated=terminated,
            truncated=truncated,
            evaluation=ep.evaluation,
            end_stamp_ns=t,
        )
        self.episodes += 1
        self._episode = None
        return summary
