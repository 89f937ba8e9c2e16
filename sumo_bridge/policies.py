"""Scripted lane-change policies on the points of :mod:`sumo_bridge.observation`.

Baselines that show the scenario needs *timing* (section 5.1: "the agent determines the moment
to change a lane"): changing at once or at random collides often, waiting for a gap does not.
Used by ``bench/sumo_env.py`` and the tests; not by the learner.
"""

from __future__ import annotations

import numpy as np

from sumo_bridge.observation import SLOT_NAMES, field_index

__all__ = ["keep_policy", "immediate_policy", "RandomPolicy", "gap_acceptance_policy"]

_LANE, _TARGET = field_index("lane"), field_index("target_lane")
_PRESENT, _GAP, _REL = field_index("present"), field_index("gap"), field_index("rel_speed")
_ROW = {name: 1 + i for i, name in enumerate(SLOT_NAMES)}


def _direction(points: np.ndarray) -> int:
    """+1 if the target lane is to the left, -1 to the right, 0 if the ego is on it."""
    lane, target = points[0, _LANE], points[0, _TARGET]
    return 0 if lane == target else (1 if target > lane else -1)


def keep_policy(points: np.ndarray) -> int:
    """Never change lanes."""
    return 0


def immediate_policy(points: np.ndarray) -> int:
    """Change towards the target lane at every step, whatever the traffic."""
    d = _direction(points)
    return 0 if d == 0 else (1 if d > 0 else 2)


class RandomPolicy:
    """Uniformly random actions (seeded)."""

    def __init__(self, seed: int = 0) -> None:
        self._rng = np.random.default_rng(seed)

    def __call__(self, points: np.ndarray) -> int:
        return int(self._rng.integers(3))


def gap_acceptance_policy(
    points: np.ndarray, lead_gap: float = 2.0, follow_gap: float = 3.0, time_headway: float = 1.0
) -> int:
    """Change towards the target lane only into a gap that is big enough.

    Accepts when the target-side leader is absent or at least ``lead_gap + time_headway *
    closing speed`` metres ahead, and likewise for the target-side follower (closing speed =
    how fast the gap shrinks; 0 if it grows). A classic gap-acceptance rule.
    """
    d = _direction(points)
    if d == 0:
        return 0
    side = "left" if d > 0 else "right"
    leader, follower = points[_ROW[f"{side}_leader"]], points[_ROW[f"{side}_follower"]]
    lead_ok = leader[_PRESENT] < 0.5 or leader[_GAP] >= lead_gap + time_headway * max(0.0, -leader[_REL])
    follow_ok = follower[_PRESENT] < 0.5 or follower[_GAP] >= follow_gap + time_headway * max(0.0, follower[_REL])
    if lead_ok and follow_ok:
        return 1 if d > 0 else 2
    return 0
