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

* inputs that could poison the learner never enter it: a state whose points or observation hold
  a NaN/inf or a value beyond float32's range, and a reward that is not finite or exceeds
  ``max_abs_reward`` in magnitude (1e300 would be stored as float32 ``inf``; 1e30 is finite but
  overflows the squared TD loss), raise ``ValueError`` before anything is buffered (the node
  counts them as malformed messages);
* a second message of a topic for a stamp already buffered -> ``duplicate_state`` /
  ``duplicate_reward``, ignored;
* with ``step_ns`` known, a message stamped off the step grid (not a multiple of ``step_ns``)
  belongs to no step: ``off_grid``, dropped before anything is buffered (kept, it would make the
  next real step look like a gap and lose its transition);
* *the window*: a message stamped at or before the last completed step, or further than
  ``max_buffered`` steps after it (``step_ns`` known), is outside the current stream ->
  ``stale_state`` / ``stale_reward``, never joined into it. Such halves are *parked* (a second
  half of a kind already parked for a stamp, or a half parked before the current stream's last
  step, is replaced by the newer message: never joined across streams). A restarted
  bridge begins again at sim time 0, and one pair stamped far in the future must not make every
  later step look stale, so the learner follows a new stream when a parked step t1 completes,
  the step before it (t1 - ``step_ns``; without ``step_ns`` the highest parked complete stamp
  below t1) completed in the parked area before it, and *no step of the current stream completed
  since that earlier step began to arrive* (the old stream went silent). Then ``stream_jumps``
  += 1, the open transition and the episode in progress are dropped (``abandoned_episodes``),
  nothing wrong is stored, and t1 is answered -- the second step of a restarted bridge, whatever
  else is parked. A single re-delivered or forged pair never moves the stream, nor do copies
  arriving while the current stream is alive;
* when step t completes while an earlier step (after the pending one) is still incomplete, that
  earlier step is lost: ``gaps`` += 1, the incomplete halves are dropped and the pending
  (s, a) is discarded instead of being joined to the wrong next state;
* with ``step_ns`` known (stamps are t_k = k * step_ns), a step lost on *both* topics is a gap
  too (without it such a loss cannot be told from normal succession);
* the bridge reports in each reward which action it applied (``applied_action``); when that is
  not the action this learner sent (the command missed the bridge's timeout and the default was
  applied), the transition stores the applied one: ``overridden_actions``;
* at most ``max_buffered`` incomplete stamps are kept (and as many parked halves, and as many
  parked complete steps); the one that arrived first is evicted (``evicted``), so a flood of
  fresh stamps cannot pin old ones.

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

__all__ = ["AgentLike", "Decision", "EpisodeSummary", "OnlineLearner", "FLOAT32_MAX", "check_finite_input"]

#: the replay stores float32: anything larger in magnitude would be stored as inf
FLOAT32_MAX = float(np.finfo(np.float32).max)  # (= der_ros.contract.FLOAT32_MAX; the core imports no contract)


def check_finite_input(what: str, values: np.ndarray) -> None:
    """ValueError naming ``what`` and the first offending entry if ``values`` hold a NaN, an inf or a
    value beyond float32's range (what would be stored as inf)."""
    arr = np.asarray(values)
    if arr.dtype.kind not in "fc":
        return
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(arr) | (np.abs(arr) > FLOAT32_MAX)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        where = index[0] if len(index) == 1 else index
        raise ValueError(f"{what}[{where}] = {arr[index].item()!r}, expected a finite number within float32 range")


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
    #: arrival order of the first message of this stamp (eviction is first in, first out)
    seq: int
    #: arrival order of the message that completed it (0 while incomplete)
    done_seq: int = 0
    obs: np.ndarray | None = None
    reward: tuple[float, bool, bool, int | None] | None = None

    @property
    def complete(self) -> bool:
        return self.obs is not None and self.reward is not None


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
    command. ``step_ns`` (optional) is the bridge's step in nanoseconds, to detect whole lost steps
    and to bound the window ahead of the last step. ``max_abs_reward`` bounds accepted rewards.
    """

    def __init__(
        self,
        agent: AgentLike,
        encode: Callable[[np.ndarray], np.ndarray] | None = None,
        max_buffered: int = 64,
        keep_lane_action: int = 0,
        step_ns: int | None = None,
        max_abs_reward: float = 1e6,
    ) -> None:
        if max_buffered < 1:
            raise ValueError(f"max_buffered = {max_buffered}, expected >= 1")
        if not 0 < max_abs_reward <= FLOAT32_MAX:
            raise ValueError(f"max_abs_reward = {max_abs_reward}, expected > 0 and <= {FLOAT32_MAX:g}")
        self.agent = agent
        self.encode = encode if encode is not None else (lambda x: x)
        self.max_buffered = max_buffered
        self.keep_lane_action = keep_lane_action
        self.step_ns = step_ns if step_ns else None
        self.max_abs_reward = float(max_abs_reward)
        #: how far ahead of the last completed step a stamp may lie (None: unbounded)
        self.window_ns = max_buffered * self.step_ns if self.step_ns else None
        self.paused = False
        self._buf: dict[int, _Half] = {}  # stamps in the window of the current stream
        self._parked: dict[int, _Half] = {}  # incomplete stamps outside it: stale copies, or a new stream
        self._parked_done: dict[int, _Half] = {}  # complete steps outside it (newest copy per stamp)
        self._seq = 0  # arrival counter of messages
        self._live_seq = 0  # arrival number of the message that last completed a step of the current stream
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
                "off_grid",
                "stream_jumps",
                "abandoned_episodes",
                "transitions",
                "actions",
                "learn_steps",
                "overridden_actions",
            )
        }

    # -- inputs ----------------------------------------------------------------------------------
    def on_state(self, stamp_ns: int, payload: np.ndarray) -> list[Decision]:
        """A ``state`` message arrived; returns the decisions of every step it completed.

        ValueError (nothing buffered) if the payload or its observation is not finite or beyond
        float32's range.
        """
        check_finite_input("state point", np.asarray(payload).reshape(-1))
        obs = np.asarray(self.encode(payload))
        check_finite_input("observation", obs.reshape(-1))
        self.counters["states"] += 1
        return self._add(int(stamp_ns), "obs", obs)

    def on_reward(
        self, stamp_ns: int, reward: float, terminated: bool, truncated: bool, applied_action: int | None = None
    ) -> list[Decision]:
        """A ``reward`` message arrived; returns the decisions of every step it completed.

        ``applied_action`` is the action the bridge reports it applied in the step that led to
        this state (None if it does not say); it replaces this learner's own action in the
        transition when they differ (a command that missed the bridge's timeout). ValueError
        (nothing buffered) if the reward is not finite or exceeds ``max_abs_reward``.
        """
        reward = float(reward)
        if not np.isfinite(reward) or abs(reward) > self.max_abs_reward:
            raise ValueError(f"reward = {reward!r}, expected a finite number with |reward| <= {self.max_abs_reward:g}")
        self.counters["rewards"] += 1
        return self._add(int(stamp_ns), "reward", (reward, bool(terminated), bool(truncated), applied_action))

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
    def _in_window(self, stamp_ns: int) -> bool:
        last = self._last_completed
        if last is None:
            return True
        return stamp_ns > last and (self.window_ns is None or stamp_ns - last <= self.window_ns)

    def _add(self, stamp_ns: int, kind: str, value: Any) -> list[Decision]:
        topic = "state" if kind == "obs" else "reward"
        self._seq += 1
        if self.step_ns is not None and stamp_ns % self.step_ns:
            self.counters["off_grid"] += 1
            return []
        if not self._in_window(stamp_ns):
            self.counters[f"stale_{topic}"] += 1
            half = self._parked.get(stamp_ns)
            if half is not None and (getattr(half, kind) is not None or half.seq <= self._live_seq):
                # a second copy, or a half older than the current stream's last step: never
                # complete it with this one (the newest wins)
                del self._parked[stamp_ns]
            half = self._slot(self._parked, stamp_ns)
            setattr(half, kind, value)
            if not half.complete:
                return []
            del self._parked[stamp_ns]
            half.done_seq = self._seq
            self._parked_done.pop(stamp_ns, None)
            self._bounded(self._parked_done)
            self._parked_done[stamp_ns] = half
            return self._follow_jump(stamp_ns)
        half = self._slot(self._buf, stamp_ns)
        if getattr(half, kind) is not None:
            self.counters[f"duplicate_{topic}"] += 1
            return []
        setattr(half, kind, value)
        return self._drain()

    def _bounded(self, table: dict[int, _Half]) -> None:
        """Make room for one more entry: evict the one that arrived first."""
        if len(table) >= self.max_buffered:
            first = min(table, key=lambda t: table[t].seq)
            del table[first]
            self.counters["evicted"] += 1

    def _slot(self, table: dict[int, _Half], stamp_ns: int) -> _Half:
        half = table.get(stamp_ns)
        if half is None:
            self._bounded(table)
            half = table[stamp_ns] = _Half(self._seq)
        return half

    def _follow_jump(self, t1: int) -> list[Decision]:
        """Parked step ``t1`` just completed: follow it if it is the second step of a new stream."""
        done = self._parked_done
        if self.step_ns is not None:
            t0 = t1 - self.step_ns
        else:
            below = [t for t in done if t < t1]
            t0 = max(below) if below else None
        first = done.get(t0) if t0 is not None else None
        if first is None or first.done_seq >= done[t1].done_seq or first.seq <= self._live_seq:
            return []  # no earlier step, or the current stream completed a step since it began
        start = first.seq  # halves that arrived before the new stream began belong to the old one
        new = done.pop(t1)
        # halves of the new stream's next step may have come early; anything else parked is stale
        nxt = (lambda t: t == t1 + self.step_ns) if self.step_ns is not None else (lambda t: t > t1)
        keep = {t: h for table in (self._buf, self._parked, done) for t, h in table.items() if nxt(t) and h.seq > start}
        self._buf = keep
        self._parked = {}
        self._parked_done = {}
        self.counters["stale_state"] -= 1  # the two halves of t1 are used after all
        self.counters["stale_reward"] -= 1
        self.counters["stream_jumps"] += 1
        if self._episode is not None:
            self.counters["abandoned_episodes"] += 1
        self._episode = None
        self._pending = None  # never join the old stream's last state to the new stream
        self._last_completed = t0
        assert new.obs is not None and new.reward is not None
        decision = self._complete(t1, new.obs, *new.reward)
        return [decision, *self._drain()]

    def _drain(self) -> list[Decision]:
        """Process every complete stamp, oldest first; earlier incomplete stamps count as gaps."""
        out: list[Decision] = []
        while True:
            complete = [t for t, h in self._buf.items() if h.complete]
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
            assert half.obs is not None and half.reward is not None
            out.append(self._complete(t, half.obs, *half.reward))

    def _complete(
        self, t: int, obs: np.ndarray, reward: float, terminated: bool, truncated: bool, applied: int | None
    ) -> Decision:
        self._last_completed = t
        self._live_seq = self._seq
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
