"""ROS-free core of the bridge's command protocol (lockstep and free-run).

The bridge publishes the state of step k stamped t_k (the *step key*, nanoseconds of global sim
time) and then needs exactly one action for step k. Commands travel over a network and can be
late, duplicated, malformed or come from a stray second publisher, so every command goes
through :meth:`CommandGate.offer`, which either accepts it for the open step or rejects it with
a :class:`Verdict` and a counter. A command is only ever applied to the step whose key it
carries:

* key of the open step, from the locked sender, one valid action -> ``ACCEPTED``;
* key of a step already closed by an accepted command -> ``DUPLICATE``;
* key of a step closed by the timeout (default action applied), or any older key -> ``LATE``;
* a key the bridge never opened (ahead of the open step, or between steps) -> ``UNKNOWN_STEP``;
* ``buttons`` not of length 1, or any axis value NaN/inf -> ``MALFORMED``;
* action outside ``0..n_actions-1`` -> ``OUT_OF_RANGE``;
* sender other than the first one ever accepted -> ``FOREIGN_SENDER`` (first-publisher lock).

Lockstep: after :meth:`open` the bridge waits for ``ACCEPTED`` or calls :meth:`expire` after
its timeout, which closes the step with :attr:`default_action` (0 = keep lane). Free-run: the
bridge steps on a timer and calls :meth:`take_latest`, which returns the last accepted action
since the previous step (or the default) — commands may answer any still-open recent step.

Terminal states are never opened (the bridge resets right away), so a command answering one is
``UNKNOWN_STEP``.

Floods: once a sender is locked, :meth:`CommandGate.screen` judges a command by its sender alone,
before the receiver decodes the rest of it (``FOREIGN_SENDER``, or ``MALFORMED`` when not even the
sender is readable): a stray publisher's flood then costs the receiver a few microseconds per
message and cannot push the locked sender's answer out of its queue (``bridge_node``).
"""

from __future__ import annotations

import enum
import math
from collections import OrderedDict
from collections.abc import Sequence

__all__ = ["Verdict", "CommandGate", "DEFAULT_ACTION"]

#: Action applied when no valid command answers a step in time: keep lane.
DEFAULT_ACTION = 0


class Verdict(enum.Enum):
    """Outcome of offering one command (value = counter name)."""

    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    LATE = "late"
    UNKNOWN_STEP = "unknown_step"
    MALFORMED = "malformed"
    OUT_OF_RANGE = "out_of_range"
    FOREIGN_SENDER = "foreign_sender"


class _Closed(enum.Enum):
    ANSWERED = 1
    TIMED_OUT = 2


class CommandGate:
    """Pairs commands with step keys; see the module docstring for the rules.

    ``history`` bounds how many closed step keys are remembered (to tell duplicates from late
    commands); older keys are all ``LATE``.
    """

    def __init__(self, n_actions: int = 3, default_action: int = DEFAULT_ACTION, history: int = 256) -> None:
        if n_actions < 1:
            raise ValueError(f"n_actions = {n_actions}, expected >= 1")
        if not 0 <= default_action < n_actions:
            raise ValueError(f"default_action = {default_action}, expected 0..{n_actions - 1}")
        self.n_actions = n_actions
        self.default_action = default_action
        self._history = history
        self._open: int | None = None
        self._closed: OrderedDict[int, _Closed] = OrderedDict()
        self._latest: int | None = None  # free-run: last accepted action since the last take
        self._latest_key: int | None = None
        self.sender: str | None = None
        self.counters: dict[str, int] = {v.value: 0 for v in Verdict}
        self.counters["timeouts"] = 0
        self.counters["opened"] = 0

    # -- step lifecycle ----------------------------------------------------------------------
    @property
    def open_key(self) -> int | None:
        """Key of the step waiting for its command (None when no step is open)."""
        return self._open

    def open(self, key: int) -> None:
        """A state stamped ``key`` was published and needs a command. Keys must increase."""
        last = self._last_key()
        if last is not None and key <= last:
            raise ValueError(f"step key {key} does not increase (last {last})")
        if self._open is not None:  # free-run: the previous step closes without its own answer
            self._close(self._open, _Closed.TIMED_OUT)
        self._open = key
        self.counters["opened"] += 1

    def expire(self) -> int:
        """Lockstep timeout: close the open step with the default action and return it."""
        if self._open is None:
            raise RuntimeError("no open step to expire")
        self._close(self._open, _Closed.TIMED_OUT)
        self._open = None
        self.counters["timeouts"] += 1
        return self.default_action

    def take_latest(self) -> int:
        """Free-run: the last accepted action since the previous call (default if none); consumes it."""
        action = self.default_action if self._latest is None else self._latest
        self._latest = None
        return action

    # -- commands ----------------------------------------------------------------------------
    def screen(self, sender: str | None) -> Verdict | None:
        """Early verdict from the sender alone (read before decoding the command), counted like
        :meth:`offer`'s: FOREIGN_SENDER once a sender is locked and this is another one, MALFORMED
        when the sender could not be read; None = decode the command and :meth:`offer` it."""
        if sender is None:
            verdict = Verdict.MALFORMED
        elif self.sender is not None and sender != self.sender:
            verdict = Verdict.FOREIGN_SENDER
        else:
            return None
        self.counters[verdict.value] += 1
        return verdict

    def offer(self, key: int, buttons: Sequence[int], axes: Sequence[float] = (), sender: str = "") -> tuple[Verdict, int]:
        """Judge one command; returns (verdict, action). The action is meaningful only if ACCEPTED.

        In lockstep an ACCEPTED command closes the open step: the caller steps the simulation.
        """
        verdict, action = self._judge(key, buttons, axes, sender)
        self.counters[verdict.value] += 1
        if verdict is Verdict.ACCEPTED:
            if self.sender is None:
                self.sender = sender
            self._close(key, _Closed.ANSWERED)
            if key == self._open:
                self._open = None
            self._latest, self._latest_key = action, key
        return verdict, action

    def _judge(self, key: int, buttons: Sequence[int], axes: Sequence[float], sender: str) -> tuple[Verdict, int]:
        if len(buttons) != 1 or any(not math.isfinite(a) for a in axes):
            return Verdict.MALFORMED, -1
        action = int(buttons[0])
        if not 0 <= action < self.n_actions:
            return Verdict.OUT_OF_RANGE, action
        if self.sender is not None and sender != self.sender:
            return Verdict.FOREIGN_SENDER, action
        if key == self._open:
            return Verdict.ACCEPTED, action
        closed = self._closed.get(key)
        if closed is _Closed.ANSWERED:
            return Verdict.DUPLICATE, action
        if closed is _Closed.TIMED_OUT:
            return Verdict.LATE, action
        oldest = next(iter(self._closed), None)
        if oldest is not None and key < oldest:
            return Verdict.LATE, action
        return Verdict.UNKNOWN_STEP, action

    # -- helpers -----------------------------------------------------------------------------
    def _last_key(self) -> int | None:
        if self._open is not None:
            return self._open
        return next(reversed(self._closed), None) if self._closed else None

    def _close(self, key: int, how: _Closed) -> None:
        self._closed[key] = how
        while len(self._closed) > self._history:
            self._closed.popitem(last=False)

    def stats(self) -> dict[str, int]:
        """Counters (stable names: accepted, duplicate, late, unknown_step, malformed, ...)."""
        return dict(self.counters)
