"""Hand-built neighbour points (``info['points']``) for the shield's tests (test/safety/)."""

from __future__ import annotations

import numpy as np

from sumo_bridge.observation import BEYOND_NAMES, empty_beyond_points, empty_points, field_index

COL = {n: field_index(n) for n in ("speed", "rel_speed", "gap", "lane", "target_lane", "present", "lane_count")}
ROW = {"left_leader": 3, "left_follower": 4, "right_leader": 5, "right_follower": 6}


def situation(ego_speed: float = 15.0, lane: int = 0, lanes: int = 2, to_diverge: float = 0.0, target_lane: int = 1,
              **slots: tuple[float, float]) -> np.ndarray:
    """Points with the ego at ``ego_speed`` on ``lane`` of ``lanes``; ``to_diverge`` is the ego row's gap (metres
    to a split, 0: none); ``slot=(gap, rel_speed)`` fills a neighbour slot."""
    pts = empty_points()
    pts[0, COL["speed"]], pts[0, COL["lane"]], pts[0, COL["lane_count"]] = ego_speed, lane, lanes
    pts[0, COL["gap"]], pts[0, COL["target_lane"]] = to_diverge, target_lane
    for name, (gap, rel) in slots.items():
        _neighbour(pts[ROW[name]], gap, rel, ego_speed, lane + (1 if name.startswith("left") else -1))
    return pts


def _neighbour(row: np.ndarray, gap: float, rel: float, ego_speed: float, lane: int) -> None:
    """Fill a present neighbour row: its gap, relative speed, speed and lane."""
    row[COL["present"]], row[COL["gap"]], row[COL["rel_speed"]] = 1.0, gap, rel
    row[COL["speed"]] = ego_speed + rel
    row[COL["lane"]] = lane


BEYOND_ROW = {name: i for i, name in enumerate(BEYOND_NAMES)}


def beyond(ego_speed: float = 15.0, lane: int = 0, **slots: tuple[float, float]) -> np.ndarray:
    """Beyond points (the cars two lanes away, ``info['beyond_points']``) around an ego at ``ego_speed`` on ``lane``;
    ``slot=(gap, rel_speed)`` fills one of ``left2_leader, left2_follower, right2_leader, right2_follower``."""
    pts = empty_beyond_points()
    for name, (gap, rel) in slots.items():
        _neighbour(pts[BEYOND_ROW[name]], gap, rel, ego_speed, lane + (2 if name.startswith("left") else -2))
    return pts
