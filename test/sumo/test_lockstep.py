"""Unit tests of the bridge's command gate (ROS-free): pairing, rejection, timeout, sender lock."""

import math

import pytest

from sumo_bridge.lockstep import DEFAULT_ACTION, CommandGate, Verdict

S = 100_000_000  # one step of 0.1 s in ns


def test_accepts_only_the_open_step_and_closes_it():
    g = CommandGate()
    g.open(0)
    assert g.offer(0, [2], sender="a") == (Verdict.ACCEPTED, 2)
    assert g.open_key is None
    # a second copy of the same command never applies again
    assert g.offer(0, [2], sender="a")[0] is Verdict.DUPLICATE
    g.open(S)
    assert g.offer(0, [1], sender="a")[0] is Verdict.DUPLICATE  # stamp of a closed step: not applied to S
    assert g.open_key == S
    assert g.offer(S, [1], sender="a") == (Verdict.ACCEPTED, 1)
    assert g.stats()["accepted"] == 2 and g.stats()["duplicate"] == 2


def test_timeout_applies_default_and_late_command_is_ignored():
    g = CommandGate()
    g.open(0)
    assert g.expire() == DEFAULT_ACTION == 0
    assert g.open_key is None
    g.open(S)
    verdict, _ = g.offer(0, [1], sender="a")  # answer to step 0 arrives after its timeout
    assert verdict is Verdict.LATE
    assert g.open_key == S  # step S still waits for its own command
    assert g.stats()["timeouts"] == 1 and g.stats()["late"] == 1


def test_keys_older_than_history_are_late_and_unknown_keys_rejected():
    g = CommandGate(history=4)
    for k in range(10):
        g.open(k * S)
        g.offer(k * S, [0], sender="a")
    assert g.offer(0, [0], sender="a")[0] is Verdict.LATE  # forgotten, but older than every remembered key
    assert g.offer(10 * S, [0], sender="a")[0] is Verdict.UNKNOWN_STEP  # never opened
    with pytest.raises(ValueError):
        g.open(9 * S)  # keys must increase


@pytest.mark.parametrize(
    "buttons,axes,verdict",
    [
        ([], (), Verdict.MALFORMED),
        ([1, 0], (), Verdict.MALFORMED),
        ([0], (math.nan,), Verdict.MALFORMED),
        ([0], (math.inf,), Verdict.MALFORMED),
        ([3], (), Verdict.OUT_OF_RANGE),
        ([-1], (), Verdict.OUT_OF_RANGE),
    ],
)
def test_bad_commands_rejected_and_step_stays_open(buttons, axes, verdict):
    g = CommandGate(n_actions=3)
    g.open(0)
    assert g.offer(0, buttons, axes, sender="a")[0] is verdict
    assert g.open_key == 0
    assert g.stats()[verdict.value] == 1
    assert g.offer(0, [1], sender="a") == (Verdict.ACCEPTED, 1)


def test_first_sender_lock():
    g = CommandGate()
    g.open(0)
    g.offer(0, [1], sender="agent-1")
    g.open(S)
    assert g.offer(S, [2], sender="intruder")[0] is Verdict.FOREIGN_SENDER
    assert g.open_key == S
    assert g.offer(S, [0], sender="agent-1") == (Verdict.ACCEPTED, 0)
    assert g.sender == "agent-1"


def test_malformed_first_command_does_not_take_the_lock():
    g = CommandGate()
    g.open(0)
    g.offer(0, [7], sender="bad")
    assert g.sender is None
    assert g.offer(0, [1], sender="good")[0] is Verdict.ACCEPTED


def test_free_run_latest_is_consumed_once():
    g = CommandGate()
    g.open(0)
    assert g.take_latest() == DEFAULT_ACTION
    g.offer(0, [2], sender="a")
    g.open(S)
    assert g.take_latest() == 2
    assert g.take_latest() == DEFAULT_ACTION  # applied once, not repeated
    g.open(2 * S)  # step S closes unanswered in free-run
    assert g.offer(S, [1], sender="a")[0] is Verdict.LATE


def test_constructor_validates():
    with pytest.raises(ValueError):
        CommandGate(n_actions=3, default_action=3)
    with pytest.raises(RuntimeError):
        CommandGate().expire()
