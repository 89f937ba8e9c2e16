"""The safety core on hand-built situations (der_ros/safety; docs/safety.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from safety_points import COL, ROW, situation

from der_ros.configuration import ConfigError, from_dict
from der_ros.safety import KEEP, RssChecker, SafetyConfig, masked_argmax, replace_unsafe, safe_longitudinal_distance
from der_ros.safety.observation_mask import ObservationMask
from der_ros.safety.sumo_check import LCA_OVERLAPPING, sumo_mask
from sumo_bridge.observation import ObservationConfig, encode_observation

CFG = SafetyConfig(kind="rss", response_time=0.5, accel_max=2.0, brake_min=4.0, brake_max=6.0)



def test_formula_textbook_values() -> None:
    # the figures of /work/shared/notes/rss.md (and ad-rss): 20/20 m/s
    assert safe_longitudinal_distance(20, 20, 1.0, 3.5, 4.0, 8.0) == pytest.approx(65.78125)
    assert safe_longitudinal_distance(20, 20, 0.5, 2.0, 4.0, 6.0) == pytest.approx(32.0416667)
    # a much faster front car: nothing to keep
    assert safe_longitudinal_distance(5, 30, 0.5, 2.0, 4.0, 6.0) == 0.0


def test_leader_gap_rss_accepts_and_refuses() -> None:
    checker = RssChecker(CFG)
    need = checker.leader_distance(15.0, 13.0)  # ego behind a leader 2 m/s slower
    assert 0 < need < 30
    assert checker.mask(situation(left_leader=(need + 0.5, -2.0)))[1]
    assert not checker.mask(situation(left_leader=(need - 0.5, -2.0)))[1]


def test_follower_gap_rss_accepts_and_refuses() -> None:
    checker = RssChecker(CFG)
    need = checker.follower_distance(10.0, 11.0)  # a follower 1 m/s faster than the ego
    assert 0 < need < 30
    assert checker.mask(situation(10.0, left_follower=(need + 0.5, 1.0)))[1]
    assert not checker.mask(situation(10.0, left_follower=(need - 0.5, 1.0)))[1]
    # both sides: the right side is judged on its own slots
    pts = situation(10.0, lane=1, lanes=3, left_follower=(need - 0.5, 1.0), right_follower=(need + 0.5, 1.0))
    assert list(RssChecker(CFG).mask(pts)) == [True, False, True]


def test_missing_neighbour_imposes_nothing_and_missing_lane_is_unsafe() -> None:
    checker = RssChecker(CFG)
    assert list(checker.mask(situation())) == [True, True, False]  # lane 0 of 2: no lane on the right
    assert list(checker.mask(situation(lane=1, lanes=2))) == [True, False, True]
    # an overlap is always refused, whatever the speeds
    assert not checker.mask(situation(left_leader=(-0.5, 10.0)))[1]
    assert not checker.mask(situation(left_follower=(0.0, -10.0)))[1]


def test_malformed_state_allows_keep_only() -> None:
    checker = RssChecker(CFG)
    bad = situation(left_leader=(20.0, 0.0))
    bad[0, COL["speed"]] = math.nan
    assert list(checker.mask(bad)) == [True, False, False]
    assert list(checker.mask(np.zeros((3, 3)))) == [True, False, False]
    nan_gap = situation(left_leader=(math.nan, 0.0))
    assert list(checker.mask(nan_gap)) == [True, False, False]


def test_replace_and_mask() -> None:
    mask = np.array([True, False, True])
    assert replace_unsafe(1, mask) == (KEEP, True)
    assert replace_unsafe(2, mask) == (2, False)
    assert replace_unsafe(0, mask) == (0, False)
    assert replace_unsafe(1, None) == (1, False)
    assert masked_argmax(np.array([0.0, 5.0, 1.0]), mask) == 2
    assert masked_argmax(np.array([0.0, 5.0, 1.0]), None) == 1
    assert masked_argmax(np.array([3.0, 5.0, 1.0]), np.array([True, False, False])) == 0


def test_observation_mask_matches_points_mask() -> None:
    """The learner's target mask (from stored observations) agrees with the checker on points."""
    obs_cfg = ObservationConfig()
    checker, from_obs = RssChecker(CFG), ObservationMask(CFG, obs_cfg)
    rng = np.random.default_rng(0)
    rows, masks = [], []
    for _ in range(400):
        slots = {}
        for name in ROW:
            if rng.random() < 0.7:
                slots[name] = (float(rng.uniform(-3, 29.5)), float(rng.uniform(-8, 8)))
        pts = situation(float(rng.uniform(2, 19)), int(rng.integers(0, 3)), 3, **slots)
        rows.append(encode_observation(pts, obs_cfg))
        masks.append(checker.mask(pts))
    got = from_obs(np.stack(rows))
    want = np.stack(masks)
    assert want[:, 1].any() and not want[:, 1].all()  # both verdicts occur
    # float32 rounding of the observation may flip a gap within a millimetre of the boundary only
    assert (got != want).mean() < 0.01


def test_sumo_mask_reads_blocked_and_overlapping_bits() -> None:
    class Vehicle:
        def __init__(self, states: dict[int, int]) -> None:
            self.states = states

        def getLaneChangeState(self, vid: str, direction: int) -> tuple[int, int]:
            return self.states[direction], 0

    class Api:
        def __init__(self, states: dict[int, int]) -> None:
            self.vehicle = Vehicle(states)

    pts = situation(lane=1, lanes=3)
    assert list(sumo_mask(Api({1: 0, -1: 0}), "ego", pts)) == [True, True, True]
    assert list(sumo_mask(Api({1: 512, -1: LCA_OVERLAPPING}), "ego", pts)) == [True, False, False]  # left leader blocks
    assert list(sumo_mask(Api({1: 0, -1: 0}), "ego", situation(lane=0, lanes=2))) == [True, True, False]


def test_config_refuses_bad_values() -> None:
    with pytest.raises(ConfigError, match="kind"):
        from_dict(SafetyConfig, {"kind": "bogus"})
    with pytest.raises(ConfigError, match="brake_min"):
        from_dict(SafetyConfig, {"brake_min": 0.0})
    with pytest.raises(ConfigError, match="mode"):
        from_dict(SafetyConfig, {"mode": "veto"})


def test_command_filter_fails_safe() -> None:
    from der_ros.safety.command_filter import CommandFilter

    checker = RssChecker(CFG)
    f = CommandFilter(checker.mask, max_state_age=0.5)
    free = situation()  # nothing on the left: a change is safe
    blocked = situation(left_leader=(1.0, -5.0))
    f.on_state(100, free, now=10.0)
    assert (f.decide(100, 1, now=10.1).verdict, f.decide(100, 1, now=10.1).applied) == ("pass", 1)
    assert f.decide(100, 1, now=10.7).verdict == "stale"  # the state is older than 0.5 s
    assert f.decide(999, 1, now=10.1).verdict == "no_state"
    d = f.decide(999, 0, now=10.1)
    assert (d.verdict, d.applied, d.intervened) == ("pass", 0, False)  # keep needs no state
    f.on_state(200, blocked, now=11.0)
    d = f.decide(200, 1, now=11.0)
    assert (d.verdict, d.applied, d.intervened) == ("unsafe", 0, True)
    assert f.decide(100, 1, now=11.0).verdict == "stale"  # a newer state came since
    f.on_state(300, None, now=12.0)  # a state that could not be read
    assert f.decide(300, 2, now=12.0).verdict == "malformed"
    assert f.decide(300, 7, now=12.0).verdict == "malformed"
    assert f.interventions == 6 and f.counters["pass"] == 3  # two passes of the change, one keep


def test_a_command_that_overtakes_its_state_waits_for_it() -> None:
    """Command and state come from different publishers: a lane change whose state has not arrived is
    parked, answered when its state comes, and becomes keep lane (no_state) after max_command_wait."""
    from der_ros.safety.command_filter import CommandFilter

    f = CommandFilter(RssChecker(CFG).mask, max_state_age=0.5, max_command_wait=0.25)
    free = situation()
    assert f.command(100, 1, now=10.0) is None  # parked: no state of stamp 100 yet
    assert f.expire(now=10.1) == []  # still within the wait
    (d,) = f.on_state(100, free, now=10.2)
    assert (d.stamp, d.verdict, d.applied) == (100, "pass", 1)
    assert f.command(200, 1, now=11.0) is None
    (d,) = f.expire(now=11.3)  # its state never came
    assert (d.stamp, d.verdict, d.applied) == (200, "no_state", 0)
    assert f.command(300, 1, now=12.0) is None
    (d,) = f.on_state(400, free, now=12.1)  # a newer state: 300's was lost
    assert (d.stamp, d.verdict) == (300, "no_state")
    assert f.command(250, 1, now=12.2).verdict == "no_state"  # older than the latest state: never parked
    assert f.command(500, 0, now=12.3).verdict == "pass"  # keep lane needs no state, never waits
    g = CommandFilter(RssChecker(CFG).mask, max_states=2)
    for k in (1, 2, 3):
        assert g.command(k, 2, now=0.0) is None
    (d,) = g.expire(now=0.0)  # bounded: the oldest parked command is answered at once
    assert (d.stamp, d.verdict) == (1, "no_state")
