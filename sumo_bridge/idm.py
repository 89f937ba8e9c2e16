"""The Intelligent Driver Model (Treiber, Hennecke and Helbing 2000): a car-follower's acceleration.

Used by :mod:`sumo_bridge.mobil` to judge lane changes by the accelerations they cause; the ego of
the IDM+MOBIL baseline drives with SUMO's own IDM (the exit scenario's vType ``ego_idm``, same values
as :class:`IdmParams`), so the model it reasons with is the one it drives with. No SUMO, no ROS.

    a = a_max [1 - (v / v0)^delta - (s* / s)^2],   s* = s0 + v T + v (v - v_lead) / (2 sqrt(a_max b))

The defaults are the motorway values of Treiber and Kesting, *Traffic Flow Dynamics* (2013, table
11.2): v0 = 120 km/h, T = 1 s, s0 = 2 m, a = 1 m/s^2, b = 1.5 m/s^2, delta = 4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["IdmParams", "idm_acceleration", "MIN_GAP"]

#: the gap (m) an IDM acceleration is computed with when the gap given is smaller (an overlap): the
#: acceleration stays finite (a very hard braking) instead of dividing by zero
MIN_GAP = 0.01


@dataclass(frozen=True)
class IdmParams:
    """IDM parameters (m, s, m/s, m/s^2)."""

    desired_speed: float = 33.33
    """v0: the free-road speed (the exit's motorway limit, 120 km/h)"""
    time_headway: float = 1.0
    """T: the desired time gap to the leader"""
    min_gap: float = 2.0
    """s0: the gap kept at standstill"""
    max_accel: float = 1.0
    """a: the maximum acceleration"""
    comfort_decel: float = 1.5
    """b: the comfortable deceleration (positive)"""
    delta: float = 4.0
    """the free-road exponent"""


def idm_acceleration(speed: float, gap: float | None, leader_speed: float | None, p: IdmParams) -> float:
    """The IDM acceleration of a vehicle at ``speed`` behind a leader ``gap`` metres ahead (bumper to
    bumper) driving at ``leader_speed``; ``gap`` None = no leader (free road)."""
    free = 1.0 - (max(speed, 0.0) / p.desired_speed) ** p.delta
    if gap is None or leader_speed is None:
        return p.max_accel * free
    s_star = p.min_gap + max(0.0, speed * p.time_headway + speed * (speed - leader_speed)
                             / (2.0 * math.sqrt(p.max_accel * p.comfort_decel)))  # fmt: skip
    return p.max_accel * (free - (s_star / max(gap, MIN_GAP)) ** 2)
