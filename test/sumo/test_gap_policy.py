"""What the gap-acceptance baseline decides (sumo_bridge.policies.gap_acceptance_policy), on hand-built
situations: accept when the target-side leader is absent or at least lead_gap + time_headway x closing
speed ahead, and likewise for the target-side follower; never look at the other side."""

from __future__ import annotations

import numpy as np
import pytest

from sumo_bridge.observation import SLOT_NAMES, empty_points, field_index
from sumo_bridge.policies import gap_acceptance_policy

KEEP, LEFT, RIGHT = 0, 1, 2
COL = {name: field_index(name) for name in ("lane", "target_lane", "present", "gap", "rel_speed")}
ROW = {name: 1 + i for i, name in enumerate(SLOT_NAMES)}


def situation(lane: int, target: int, **vehicles: tuple[float, float]) -> np.ndarray:
    """Ego on ``lane`` heading for ``target``; ``slot=(gap m, rel_speed m/s)`` puts a vehicle in a slot
    (rel_speed = its speed minus the ego's)."""
    pts = empty_points()
    pts[0, COL["lane"]], pts[0, COL["target_lane"]] = lane, target
    for slot, (gap, rel) in vehicles.items():
        pts[ROW[slot], COL["present"]] = 1.0
        pts[ROW[slot], COL["gap"]] = gap
        pts[ROW[slot], COL["rel_speed"]] = rel
    return pts


def test_on_the_target_lane_it_keeps_whatever_the_traffic():
    assert gap_acceptance_policy(situation(1, 1)) == KEEP
    assert gap_acceptance_policy(situation(1, 1, left_leader=(100.0, 0.0), right_follower=(100.0, 0.0))) == KEEP


def test_an_empty_target_side_is_taken_at_once_towards_the_target():
    assert gap_acceptance_policy(situation(0, 1)) == LEFT
    assert gap_acceptance_policy(situation(2, 0)) == RIGHT  # two lanes away: first step to the right


@pytest.mark.parametrize(("rel", "needed"), [(-3.0, 2.0 + 3.0), (0.0, 2.0), (5.0, 2.0)])
def test_the_leader_gap_must_cover_lead_gap_plus_headway_times_closing_speed(rel, needed):
    """A slower leader (rel < 0) closes at -rel m/s: 2 m + 1 s x 3 m/s = 5 m; a faster one needs 2 m."""
    assert gap_acceptance_policy(situation(0, 1, left_leader=(needed, rel))) == LEFT
    assert gap_acceptance_policy(situation(0, 1, left_leader=(needed - 0.01, rel))) == KEEP


@pytest.mark.parametrize(("rel", "needed"), [(4.0, 3.0 + 4.0), (0.0, 3.0), (-2.0, 3.0)])
def test_the_follower_gap_must_cover_follow_gap_plus_headway_times_closing_speed(rel, needed):
    """A faster follower (rel > 0) closes at rel m/s: 3 m + 1 s x 4 m/s = 7 m; a slower one needs 3 m."""
    assert gap_acceptance_policy(situation(1, 0, right_follower=(needed, rel))) == RIGHT
    assert gap_acceptance_policy(situation(1, 0, right_follower=(needed - 0.01, rel))) == KEEP


def test_both_target_side_gaps_must_be_acceptable():
    ok_lead, ok_follow = (10.0, 0.0), (10.0, 0.0)
    assert gap_acceptance_policy(situation(0, 1, left_leader=ok_lead, left_follower=ok_follow)) == LEFT
    assert gap_acceptance_policy(situation(0, 1, left_leader=(1.0, 0.0), left_follower=ok_follow)) == KEEP
    assert gap_acceptance_policy(situation(0, 1, left_leader=ok_lead, left_follower=(2.9, 0.0))) == KEEP


def test_only_the_target_side_is_looked_at():
    """Vehicles right next to the ego on the other side or in its own lane do not stop a change."""
    busy = dict(right_leader=(0.1, -10.0), right_follower=(0.1, 10.0), leader=(0.5, -5.0), follower=(0.5, 5.0))
    assert gap_acceptance_policy(situation(0, 1, **busy)) == LEFT
    mirrored = dict(left_leader=(0.1, -10.0), left_follower=(0.1, 10.0))
    assert gap_acceptance_policy(situation(1, 0, **mirrored)) == RIGHT


def test_the_thresholds_are_the_parameters():
    pts = situation(0, 1, left_leader=(6.0, -2.0), left_follower=(6.0, 1.0))
    assert gap_acceptance_policy(pts) == LEFT  # needs 2 + 2 = 4 ahead and 3 + 1 = 4 behind
    assert gap_acceptance_policy(pts, lead_gap=4.5) == KEEP  # 4.5 + 2 = 6.5 > 6
    assert gap_acceptance_policy(pts, follow_gap=5.5) == KEEP  # 5.5 + 1 = 6.5 > 6
    assert gap_acceptance_policy(pts, time_headway=2.5) == KEEP  # 2 + 2.5 x 2 = 7 > 6
    assert gap_acceptance_policy(pts, time_headway=0.0, lead_gap=6.0, follow_gap=6.0) == LEFT
