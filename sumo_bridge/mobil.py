"""MOBIL, "minimizing overall braking induced by lane changes" (Kesting, Treiber and Helbing 2007), with
a mandatory-exit bias: the lane-change rule of the IDM+MOBIL baseline (``der baselines``: ``mobil``).

A change to the left or right lane is judged by IDM accelerations (:mod:`sumo_bridge.idm`) of the
three drivers it affects -- the ego ``c``, its new follower ``n`` on the target lane and its old
follower ``o`` -- now (``a``) and after the change (``ã``):

* **safety**: the new follower need not brake harder than ``b_safe`` (``ã_n >= -b_safe``), nor the
  ego behind its new leader (``ã_c >= -b_safe``, as highway-env also asks), and neither gap overlaps;
* **incentive**: ``ã_c - a_c + p (ã_n - a_n + ã_o - a_o) + bias > Δa_th``, politeness ``p``;
* **exit bias** (MOBIL's bias term for strategic, mandatory changes): toward the lane(s) that lead to
  the exit ``+bias``, away from them ``-bias``, with ``bias = exit_bias * min(1, n * exit_lookahead / d)``
  growing as the diverge nears: ``d`` metres to it, ``n`` the lane changes still needed from the
  lane farther from the exit of the two. With ``d <= n * exit_lookahead`` it is ``exit_bias`` in full.

Of the changes that pass both criteria the one with the larger incentive is taken, otherwise the ego
keeps its lane. MOBIL chooses only among keep / left / right: the speed is the car-following model's
(SUMO's IDM drives the ego), so a scenario's faster / slower actions are never used.

Inputs are the env's points (:mod:`sumo_bridge.observation`): the six neighbour slots within the
neighbour range (30 m); a slot that is empty counts as free road. The ego row's ``gap`` carries the
distance to the diverge in scenarios with a goal edge (0 otherwise: the bias is then in full).

Parameters (:class:`MobilParams`): p = 0.5, Δa_th = 0.2 m/s^2, b_safe = 4 m/s^2 by default, the
"typical values" of Treiber's MOBIL page (p 0-0.5, b_safe 4, threshold 0.2); the exit bias is tuned
per scenario on tuning seeds and frozen in ``config/baselines.yaml`` (research/tuning/exit_rules.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sumo_bridge.idm import IdmParams, idm_acceleration
from sumo_bridge.observation import SLOT_NAMES, field_index

__all__ = ["MobilParams", "Neighbour", "Situation", "situation_from_points", "exit_bias", "change_incentive",
           "mobil_decision", "mobil_policy"]  # fmt: skip


@dataclass(frozen=True)
class MobilParams:
    """MOBIL's parameters (m/s^2 unless said) and the IDM it judges accelerations with."""

    politeness: float = 0.5
    """p: weight of the followers' acceleration changes (0 selfish, 1 counts them as its own)"""
    threshold: float = 0.2
    """Δa_th: the incentive a change must exceed"""
    safe_decel: float = 4.0
    """b_safe: the hardest braking a change may impose on the new follower (and on the ego)"""
    exit_bias: float = 1.0
    """the largest bias toward the exit lane (m/s^2), reached within n * exit_lookahead of the diverge"""
    exit_lookahead: float = 100.0
    """metres per lane change still needed within which the exit bias is in full; farther it falls as 1/d"""
    idm: IdmParams = field(default_factory=IdmParams)
    """the car-following model the accelerations are computed with (the ego drives with the same)"""


@dataclass(frozen=True)
class Neighbour:
    """A vehicle near the ego: bumper-to-bumper ``gap`` to the ego (m) and its ``speed`` (m/s)."""

    gap: float
    speed: float


@dataclass(frozen=True)
class Situation:
    """What MOBIL needs of one moment: the ego and its six neighbours (None = no vehicle in range)."""

    speed: float
    length: float
    lane: int
    lane_count: int
    leader: Neighbour | None = None
    follower: Neighbour | None = None
    left_leader: Neighbour | None = None
    left_follower: Neighbour | None = None
    right_leader: Neighbour | None = None
    right_follower: Neighbour | None = None
    target_lane: int = -1
    """the lane that leads to the exit (-1: none, no bias)"""
    exit_distance: float = 0.0
    """metres to the diverge (<= 0: unknown or reached, the bias is in full)"""


_SPEED, _GAP, _LANE = field_index("speed"), field_index("gap"), field_index("lane")
_TARGET, _PRESENT, _LANES, _LENGTH = (field_index(n) for n in ("target_lane", "present", "lane_count", "length"))


def situation_from_points(points: np.ndarray) -> Situation:
    """The :class:`Situation` of the env's points (row 0 the ego, rows 1.. the slots of ``SLOT_NAMES``)."""
    ego = points[0]
    slots = {name: (Neighbour(float(row[_GAP]), float(row[_SPEED])) if row[_PRESENT] > 0.5 else None)
             for name, row in zip(SLOT_NAMES, points[1:])}  # fmt: skip
    return Situation(speed=float(ego[_SPEED]), length=float(ego[_LENGTH]), lane=int(ego[_LANE]),
                     lane_count=int(ego[_LANES]), target_lane=int(ego[_TARGET]), exit_distance=float(ego[_GAP]),
                     **slots)  # fmt: skip


def _acc(speed: float, leader: Neighbour | None, gap: float | None, idm: IdmParams) -> float:
    return idm_acceleration(speed, gap, None if leader is None else leader.speed, idm)


def exit_bias(s: Situation, direction: int, p: MobilParams) -> float:
    """The bias term of a change by ``direction`` (+1 left, -1 right): positive toward the exit lane,
    negative away from it, 0 without a target lane."""
    if s.target_lane < 0 or direction == 0:
        return 0.0
    now, after = abs(s.lane - s.target_lane), abs(s.lane + direction - s.target_lane)
    if now == after:
        return 0.0
    n = max(now, after)
    d = s.exit_distance
    size = p.exit_bias if d <= 0.0 else p.exit_bias * min(1.0, n * p.exit_lookahead / d)
    return size if after < now else -size


def change_incentive(s: Situation, direction: int, p: MobilParams) -> float | None:
    """MOBIL's incentive of a change by ``direction`` (+1 left, -1 right), None if the lane does not
    exist or the change is unsafe (see the module docstring)."""
    if not 0 <= s.lane + direction < s.lane_count:
        return None
    side = "left" if direction > 0 else "right"
    new_leader: Neighbour | None = getattr(s, f"{side}_leader")
    new_follower: Neighbour | None = getattr(s, f"{side}_follower")
    idm = p.idm
    # safety: no overlap, and neither the new follower nor the ego brakes harder than b_safe
    if (new_leader is not None and new_leader.gap <= 0.0) or (new_follower is not None and new_follower.gap <= 0.0):
        return None
    ego_after = _acc(s.speed, new_leader, None if new_leader is None else new_leader.gap, idm)
    if ego_after < -p.safe_decel:
        return None
    gain_new = 0.0
    if new_follower is not None:
        behind_ego = idm_acceleration(new_follower.speed, new_follower.gap, s.speed, idm)
        if behind_ego < -p.safe_decel:
            return None
        # before the change its leader is the ego's new leader: its gap reaches across the ego's place
        gap_now = None if new_leader is None else new_follower.gap + s.length + new_leader.gap
        gain_new = behind_ego - _acc(new_follower.speed, new_leader, gap_now, idm)
    gain_old = 0.0
    if s.follower is not None:
        gap_after = None if s.leader is None else s.follower.gap + s.length + s.leader.gap
        gain_old = _acc(s.follower.speed, s.leader, gap_after, idm) - idm_acceleration(
            s.follower.speed, s.follower.gap, s.speed, idm)  # fmt: skip
    ego_now = _acc(s.speed, s.leader, None if s.leader is None else s.leader.gap, idm)
    return ego_after - ego_now + p.politeness * (gain_new + gain_old) + exit_bias(s, direction, p)


def mobil_decision(s: Situation, p: MobilParams) -> int:
    """+1 (change left), -1 (change right) or 0 (keep): the safe change whose incentive exceeds Δa_th
    by the most (ties: right, toward the usual exit side), else keep."""
    best, best_gain = 0, -math.inf
    for direction in (-1, 1):
        gain = change_incentive(s, direction, p)
        if gain is not None and gain > p.threshold and gain > best_gain:
            best, best_gain = direction, gain
    return best


def mobil_policy(points: np.ndarray, p: MobilParams) -> int:
    """The env action of :func:`mobil_decision` on the env's points: 0 keep, 1 left, 2 right."""
    d = mobil_decision(situation_from_points(points), p)
    return 0 if d == 0 else (1 if d > 0 else 2)
