"""Which actions are safe in a state: the RSS check on the ego and its observed neighbour slots.

Input is the points array of :mod:`sumo_bridge.observation` (what the env's ``info["points"]`` and
the graph's ``state`` cloud carry): row 0 the ego, rows 1.. the slots ``leader, follower,
left_leader, left_follower, right_leader, right_follower`` with absolute speed, relative speed and
the bumper-to-bumper gap along the road.

A lane change to a side is safe when

* the ego's lane has a lane on that side (``lane_count``; no lane there -> unsafe),
* the new leader on that side (if observed) is farther ahead than the RSS safe distance with the
  ego as the rear car (braking at ``ego_brake``, by default ``brake_min``: what the ego can really do), and
* the new follower on that side (if observed) is farther behind than the RSS safe distance with
  the follower as the rear car,

each distance from :func:`der_ros.safety.rss.safe_longitudinal_distance` plus ``margin``. An empty
slot means no vehicle within the neighbour range (30 m): it imposes nothing, except that with
``unobserved_speed`` > 0 an empty *follower* slot stands for a car at the range driving at that speed
(the fastest car that may be just out of sight; an unseen leader is the ego's own car-following's
business, as the own-lane leader is). With ``beyond_lane`` and the beyond points (the env's
``info["beyond_points"]``: the nearest car ahead and behind two lanes to each side), a car on the lane
beyond the target lane must keep the same RSS distances as if it were in the target lane already: it may
change into that lane in the same step as the ego (exit scenario, cause C). Keep lane is always
safe. A malformed ego row (non-finite numbers, a wrong shape) allows keep only: the shield fails
safe. What this does *not* cover is in docs/safety.md.
"""

from __future__ import annotations

import math

import numpy as np

from der_ros.safety.config import SafetyConfig
from der_ros.safety.rss import safe_longitudinal_distance
from sumo_bridge.observation import BEYOND_NAMES, POINT_FIELDS, SLOT_NAMES, ObservationConfig

__all__ = ["RssChecker", "N_ACTIONS", "SIDES"]

#: keep, left, right (``ACTION_NAMES``)
N_ACTIONS = 3
#: action -> (side name of its slots, lane offset)
SIDES: dict[int, tuple[str, int]] = {1: ("left", 1), 2: ("right", -1)}

_COL = {name: i for i, name in enumerate(POINT_FIELDS)}
_SPEED, _REL, _GAP, _LANE = _COL["speed"], _COL["rel_speed"], _COL["gap"], _COL["lane"]
_PRESENT, _LANES, _TARGET = _COL["present"], _COL["lane_count"], _COL["target_lane"]
_ROW = {name: 1 + i for i, name in enumerate(SLOT_NAMES)}
_SHAPE = (1 + len(SLOT_NAMES), len(POINT_FIELDS))
_BEYOND_ROW = {name: i for i, name in enumerate(BEYOND_NAMES)}
_BEYOND_SHAPE = (len(BEYOND_NAMES), len(POINT_FIELDS))


class RssChecker:
    """``mask(points)``: a bool array over (keep, left, right), True where the action is safe."""

    def __init__(self, cfg: SafetyConfig, neighbour_range: float = ObservationConfig.neighbour_range) -> None:
        self.cfg = cfg
        self._params = (cfg.response_time, cfg.accel_max, cfg.brake_min, cfg.brake_max)
        #: where an empty slot's unseen car may be (the observation's neighbour range, metres of gap)
        self.neighbour_range = float(neighbour_range)
        self._unseen = (cfg.response_time, cfg.accel_max, cfg.unobserved_brake, cfg.brake_max)
        #: the ego as the rear car (a new leader): its own braking (``ego_brake``, default ``brake_min``)
        self._ego_rear = (cfg.response_time, cfg.accel_max, cfg.ego_braking, cfg.brake_max)

    def unobserved_follower_distance(self, v_ego: float) -> float:
        """Safe gap (m) to the car an empty follower slot may hide (``unobserved_speed``, braking at
        ``unobserved_brake``); 0 when ``unobserved_speed`` is 0 (an empty slot imposes nothing)."""
        if self.cfg.unobserved_speed <= 0.0:
            return 0.0
        return safe_longitudinal_distance(self.cfg.unobserved_speed, v_ego, *self._unseen) + self.cfg.margin

    def leader_distance(self, v_ego: float, v_leader: float) -> float:
        """Safe gap (m) to a new leader: the ego is the rear car, braking at ``ego_brake`` (default ``brake_min``)."""
        return safe_longitudinal_distance(v_ego, v_leader, *self._ego_rear) + self.cfg.margin

    def follower_distance(self, v_ego: float, v_follower: float) -> float:
        """Safe gap (m) to a new follower: the follower is the rear car."""
        return safe_longitudinal_distance(v_follower, v_ego, *self._params) + self.cfg.margin

    def lane_end_safe(self, v_ego: float, to_diverge: float, to_target: float, offset: int) -> bool:
        """False when a change by ``offset`` does not move toward the target lane (``to_target`` lanes away) and the
        ego, which must then stop at the diverge ``to_diverge`` metres ahead (its lane does not lead to the goal),
        would brake harder than ``brake_max`` there: no car behind may be assumed to expect that. A gap of 0 means
        no diverge ahead (ring, urban, past it)."""
        toward = (to_target > 0.0 and offset > 0) or (to_target < 0.0 and offset < 0)
        if toward or not to_diverge > 0.0:
            return True
        return v_ego * v_ego / (2.0 * to_diverge) <= self.cfg.brake_max

    def change_safe(self, points: np.ndarray | list[list[float]], action: int,
                    beyond: np.ndarray | list[list[float]] | None = None) -> bool:
        """True when the lane change ``action`` (1 left, 2 right) is safe in ``points`` (array or nested lists);
        ``beyond``: the beyond points (``BEYOND_NAMES`` rows), read only with ``beyond_lane``."""
        side, offset = SIDES[action]
        ego = points[0]
        v_ego, lane, lanes = float(ego[_SPEED]), float(ego[_LANE]), float(ego[_LANES])
        if not (math.isfinite(v_ego) and math.isfinite(lane) and math.isfinite(lanes)):
            return False
        if not 0 <= lane + offset < lanes:
            return False  # no lane on that side
        if self.cfg.lane_end and not self.lane_end_safe(v_ego, float(ego[_GAP]), float(ego[_TARGET]) - lane, offset):
            return False
        for slot, is_leader in ((f"{side}_leader", True), (f"{side}_follower", False)):
            row = points[_ROW[slot]]
            if not row[_PRESENT] > 0.5:
                if is_leader or self.cfg.unobserved_speed <= 0.0:
                    continue
                if not self.neighbour_range > self.unobserved_follower_distance(v_ego):  # the unseen car, at the range
                    return False
            elif not self._keeps_distance(row, is_leader, v_ego):
                return False
        if self.cfg.beyond_lane and beyond is not None and 0 <= lane + 2 * offset < lanes:
            return self._beyond_safe(beyond, side, v_ego)
        return True

    def _keeps_distance(self, row: np.ndarray | list[float], is_leader: bool, v_ego: float) -> bool:
        """A present neighbour ``row`` keeps the RSS distance to the ego as its new leader or follower (a
        non-finite gap or speed does not)."""
        gap, v = float(row[_GAP]), v_ego + float(row[_REL])
        if not (math.isfinite(gap) and math.isfinite(v)):
            return False
        need = self.leader_distance(v_ego, v) if is_leader else self.follower_distance(v_ego, v)
        return gap > need

    def _beyond_safe(self, beyond: np.ndarray | list[list[float]], side: str, v_ego: float) -> bool:
        """The cars two lanes to ``side`` keep the RSS distances they would need in the target lane (a car there
        may change into it in the same step as the ego); an empty slot imposes nothing."""
        for slot, is_leader in ((f"{side}2_leader", True), (f"{side}2_follower", False)):
            row = beyond[_BEYOND_ROW[slot]]
            if row[_PRESENT] > 0.5 and not self._keeps_distance(row, is_leader, v_ego):
                return False
        return True

    def mask(self, points: np.ndarray, beyond: np.ndarray | None = None) -> np.ndarray:
        """Safe actions in ``points`` (shape ``(1 + len(SLOT_NAMES), len(POINT_FIELDS))``); ``beyond``: the beyond
        points (shape ``(len(BEYOND_NAMES), len(POINT_FIELDS))``), None where they are unknown (the graph's state).
        With ``beyond_lane`` a malformed ``beyond`` allows keep only."""
        out = np.zeros(N_ACTIONS, dtype=bool)
        out[0] = True
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != _SHAPE:
            return out
        far = None
        if self.cfg.beyond_lane and beyond is not None:
            far_arr = np.asarray(beyond, dtype=np.float64)
            if far_arr.shape != _BEYOND_SHAPE:
                return out
            far = far_arr.tolist()
        rows = pts.tolist()  # plain floats: several times faster to index than numpy scalars at this size
        out[1] = self.change_safe(rows, 1, far)
        out[2] = self.change_safe(rows, 2, far)
        return out
