"""SUMO's own verdict on a lane change, for comparison with RSS (``safety.kind: sumo``).

SUMO's lane-change model evaluates, every step, whether a change to the left or right is blocked
by a leader or follower on that side (its secure gaps) or whether the ego overlaps a vehicle there
(``traci.vehicle.getLaneChangeState``). The ego's own model does not act (its lane-change mode is 0:
the agent decides), but SUMO computes the state all the same. The change is unsafe when the state
has any of the blocked bits or the overlapping bit.

Needs the simulation: in process (the gymnasium wrapper) it asks the env's ``api`` (libsumo or
TraCI); in the ROS graph only the bridge holds it (docs/safety.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from der_ros.safety.checker import N_ACTIONS, SIDES
from sumo_bridge.observation import field_index

__all__ = ["LCA_BLOCKED", "LCA_OVERLAPPING", "UNSAFE_BITS", "sumo_mask", "state_unsafe"]

#: ``traci.constants`` values (SUMO's MSLaneChanger.h), spelled here so this module needs no SUMO import
LCA_BLOCKED = 268459520  # blocked by a leader/follower on either side, insufficient space or speed
LCA_OVERLAPPING = 8192
UNSAFE_BITS = LCA_BLOCKED | LCA_OVERLAPPING
_LANE, _LANES = field_index("lane"), field_index("lane_count")


def state_unsafe(state: int) -> bool:
    """True when a ``getLaneChangeState`` state word says the change is blocked or overlapping."""
    return bool(int(state) & UNSAFE_BITS)


def sumo_mask(api: Any, ego_id: str, points: np.ndarray | None = None) -> np.ndarray:
    """Safe actions (keep, left, right) by SUMO's verdict for vehicle ``ego_id``.

    ``points`` (optional) rules out a side with no lane first (SUMO answers for a missing lane too,
    but not always with a blocked bit). Any error asking SUMO (the ego gone) allows keep only.
    """
    out = np.zeros(N_ACTIONS, dtype=bool)
    out[0] = True
    for action, (_, offset) in SIDES.items():
        if points is not None:
            lane, lanes = float(points[0][_LANE]), float(points[0][_LANES])
            if not 0 <= lane + offset < lanes:
                continue
        try:
            state, _ = api.vehicle.getLaneChangeState(ego_id, offset)
        except Exception:  # noqa: BLE001 - the vehicle left, or the simulation closed: fail safe
            continue
        out[action] = not state_unsafe(state)
    return out
