"""The safety node's core, ROS-free: match each command to the state it answers, and filter it.

Step protocol (:mod:`der_ros.contract`): the bridge publishes ``state`` stamped t_k; the agent
answers with a command stamped t_k. The filter keeps the last few states by stamp and, for each
command, decides:

* ``pass`` -- the state of that stamp is known, fresh, and the checker allows the command;
* ``unsafe`` -- the checker refuses it: keep lane;
* ``no_state`` -- no state of that stamp arrived (yet, or it was lost): keep lane;
* ``stale`` -- the state arrived more than ``max_state_age`` seconds before the command (wall clock),
  or a newer state has arrived since (the command answers an old situation): keep lane;
* ``malformed`` -- the state of that stamp could not be read (or the command's action is not an
  action): keep lane.

Fails safe: every doubt is keep lane, and keep lane is never refused. Counters per verdict.
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
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(VERDICTS, 0))
    interventions: int = 0
    _states: OrderedDict[int, tuple[np.ndarray | None, float]] = field(default_factory=OrderedDict)
    _latest: int | None = None

    def on_state(self, stamp: int, points: np.ndarray | None, now: float) -> None:
        """A state arrived at wall time ``now`` (None: it was malformed)."""
        self._states[int(stamp)] = (points, float(now))
        self._states.move_to_end(int(stamp))
        while len(self._states) > self.max_states:
            self._states.popitem(last=False)
        if self._latest is None or stamp > self._latest:
            self._latest = int(stamp)

    def decide(self, stamp: int, action: int, now: float) -> Decision:
        """The decision on a command stamped ``stamp`` proposing ``action``, received at ``now``."""
        verdict = self._verdict(int(stamp), action, now)
        applied = int(action) if verdict == "pass" else KEEP
        d = Decision(int(stamp), int(action), applied, verdict)
        self.counters[verdict] += 1
        self.interventions += d.intervened
        return d

    def _verdict(self, stamp: int, action: int, now: float) -> str:
        if not isinstance(action, (int, np.integer)) or not 0 <= int(action) < N_ACTIONS:
            return "malformed"
        if int(action) == KEEP:
            return "pass"  # keep lane needs no state
        entry = self._states.get(stamp)
        if entry is None:
            return "no_state"
        points, received = entry
        if points is None:
            return "malformed"
        if now - received > self.max_state_age or (self._latest is not None and stamp < self._latest):
            return "stale"
        return "pass" if bool(self.mask(points)[int(action)]) else "unsafe"
