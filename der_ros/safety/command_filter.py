"""The safety node's core, ROS-free: match each command to the state it answers, and filter it.

Step protocol (:mod:`der_ros.contract`): the bridge publishes ``state`` stamped t_k; the agent
answers with a command stamped t_k. The filter keeps the last few states by stamp and, for each
command, decides:

* ``pass`` -- the state of that stamp is known, fresh, and the checker allows the command;
* ``unsafe`` -- the checker refuses it: keep lane;
* ``no_state`` -- no state of that stamp arrived within ``max_command_wait`` seconds of the command
  (or a newer state arrived first: it was lost): keep lane;
* ``stale`` -- the state arrived more than ``max_state_age`` seconds before the command (wall clock),
  or a newer state has arrived since (the command answers an old situation): keep lane;
* ``malformed`` -- the state of that stamp could not be read (or the command's action is not an
  action): keep lane.

Fails safe: every doubt is keep lane, and keep lane is never refused. Counters per verdict.

The agent's command and the bridge's state travel on different topics from different publishers, so
under load the command can overtake its state. :meth:`CommandFilter.command` therefore parks a lane
change whose state has not arrived yet; :meth:`CommandFilter.on_state` answers it when the state comes,
and :meth:`CommandFilter.expire` answers it ``no_state`` after ``max_command_wait`` seconds (the node
calls it from a timer). :meth:`CommandFilter.decide` is the immediate verdict without parking.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from der_ros.safety.apply import KEEP
from der_ros.safety.checker import N_ACTIONS

__all__ = ["Decision", "CommandFilter", "VERDICTS"]

VERDICTS: tuple[str, ...] = ("pass", "unsafe", "no_state", "stale", "malformed")


@dataclass(frozen=True)
class Decision:
    """What the safety node publishes for one command."""

    stamp: int
    proposed: int
    applied: int
    verdict: str  # one of VERDICTS

    @property
    def intervened(self) -> bool:
        """The command was changed (a proposed keep that stays keep is no intervention)."""
        return self.applied != self.proposed


@dataclass
class CommandFilter:
    """Pairs commands with states by stamp; ``mask(points)`` is the checker (e.g. ``RssChecker.mask``)."""

    mask: Callable[[np.ndarray], np.ndarray]
    max_state_age: float = 1.0
    max_states: int = 16
    #: seconds a lane change may wait for its state before it becomes keep lane (``no_state``)
    max_command_wait: float = 0.25
    #: the scenario's action count: actions 3 .. n_actions - 1 are speed actions, passed like keep lane
    n_actions: int = N_ACTIONS
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(VERDICTS, 0))
    interventions: int = 0
    _states: OrderedDict[int, tuple[np.ndarray | None, float]] = field(default_factory=OrderedDict)
    _latest: int | None = None
    #: lane changes waiting for their state: stamp -> (action, wall time received)
    _parked: OrderedDict[int, tuple[int, float]] = field(default_factory=OrderedDict)
    _overflow: list[Decision] = field(default_factory=list)

    def on_state(self, stamp: int, points: np.ndarray | None, now: float) -> list[Decision]:
        """A state arrived at wall time ``now`` (None: it was malformed). Returns the decisions on parked
        commands it settles: the command of this stamp, and any older one (its state was lost)."""
        self._states[int(stamp)] = (points, float(now))
        self._states.move_to_end(int(stamp))
        while len(self._states) > self.max_states:
            self._states.popitem(last=False)
        if self._latest is None or stamp > self._latest:
            self._latest = int(stamp)
        settled = [k for k in self._parked if k <= int(stamp)]
        return [self.decide(k, self._parked.pop(k)[0], now) for k in settled]

    def command(self, stamp: int, action: int, now: float) -> Decision | None:
        """A command arrived at ``now``: its decision, or None if it waits for its state (parked)."""
        stamp = int(stamp)
        waits = (isinstance(action, (int, np.integer)) and 0 < int(action) < N_ACTIONS and stamp not in self._states
                 and (self._latest is None or stamp > self._latest))  # fmt: skip
        if not waits:
            return self.decide(stamp, action, now)
        if stamp in self._parked:  # a second command for the same stamp: the first one is answered as it is
            return self.decide(stamp, action, now)
        self._parked[stamp] = (int(action), float(now))
        while len(self._parked) > self.max_states:
            old, (act, _) = self._parked.popitem(last=False)
            self._overflow.append(self.decide(old, act, now))
        return None

    def expire(self, now: float) -> list[Decision]:
        """Decisions (``no_state``) on parked commands that waited longer than ``max_command_wait``, and on
        any parked beyond ``max_states``."""
        out, self._overflow = self._overflow, []
        for k in [k for k, (_, t) in self._parked.items() if now - t > self.max_command_wait]:
            out.append(self.decide(k, self._parked.pop(k)[0], now))
        return out

    def decide(self, stamp: int, action: int, now: float) -> Decision:
        """The decision on a command stamped ``stamp`` proposing ``action``, received at ``now``."""
        verdict = self._verdict(int(stamp), action, now)
        applied = int(action) if verdict == "pass" else KEEP
        d = Decision(int(stamp), int(action), applied, verdict)
        self.counters[verdict] += 1
        self.interventions += d.intervened
        return d

    def _verdict(self, stamp: int, action: int, now: float) -> str:
        if not isinstance(action, (int, np.integer)) or not 0 <= int(action) < max(self.n_actions, N_ACTIONS):
            return "malformed"
        if int(action) == KEEP or int(action) >= N_ACTIONS:
            return "pass"  # keep lane and the speed actions need no state (SUMO's car-following keeps them safe)
        entry = self._states.get(stamp)
        if entry is None:
            return "no_state"
        points, received = entry
        if points is None:
            return "malformed"
        if now - received > self.max_state_age or (self._latest is not None and stamp < self._latest):
            return "stale"
        return "pass" if bool(self.mask(points)[int(action)]) else "unsafe"
