"""Point layout of the lane-change state and the observation vector built from it.

This module is the one contract shared by the SUMO environment, the ROS bridge node and the
agent node (docs/architecture.md, "SUMO environment" and the ``state`` topic). It imports
neither SUMO nor ROS.

Points (``info["points"]``, published as a PointCloud2 with FLOAT64 fields)
----------------------------------------------------------------------------
A float64 array of shape ``(1 + len(SLOT_NAMES), len(POINT_FIELDS))``. Row 0 is the ego
(RL-controlled) vehicle, row ``1 + i`` is neighbour slot ``SLOT_NAMES[i]``. Columns:

``x, y, z``
    Position relative to the ego in the ego frame (metres; x forward along the ego's heading,
    y to its left, z up). Row 0 is (0, 0, 0).
``speed``
    Absolute speed (m/s).
``rel_speed``
    ``speed - ego speed`` (m/s); 0 in row 0.
``gap``
    Bumper-to-bumper longitudinal gap along the road (metres): for a leader the distance from
    the ego's front bumper to the leader's rear bumper, for a follower from the follower's
    front bumper to the ego's rear bumper. Negative means the two vehicles overlap
    longitudinally (a lane change now would collide). 0 in row 0.
``lane``
    Lane index of the vehicle (SUMO: 0 = rightmost lane of the edge).
``target_lane``
    Row 0: the lane index the ego must reach (section 5.1: the inner ring lane). -1 in
    neighbour rows.
``present``
    1 if the row holds a vehicle, 0 for an empty slot (no such neighbour within the
    neighbour range). Empty rows are all zeros except ``slot``, ``lane = -1`` and
    ``target_lane = -1``.
``slot``
    0 for the ego, ``1 + i`` for ``SLOT_NAMES[i]``.
``lane_count``
    Number of lanes of the edge the vehicle is on (row 0 decides whether "left"/"right" exist).
``length``
    Vehicle length (metres).

Neighbour slots follow SUMO's own definitions (``vehicle.getLeader``, ``getFollower``,
``getLeftLeaders``, ``getLeftFollowers``, ``getRightLeaders``, ``getRightFollowers``): the
nearest vehicle ahead / behind on the ego's lane and on the lanes directly to its left and
right, within ``ObservationConfig.neighbour_range`` metres of gap (the paper's 30 m, section
5.1). "Left" is the higher lane index (SUMO counts lanes from the right).

Observation vector (``encode_observation``)
-------------------------------------------
float32, shape ``(observation_size(cfg),)``, every entry in [-1, 1]; 5 + 4 x 6 = 29 entries, 35
with the deceleration block:

* ego: ``speed / speed_scale`` (clipped to [0, 1]); ``lane / (max_lanes - 1)``;
  ``clip(target_lane - lane, -1, 1)`` (which way the target lies, 0 once on it);
  ``has_left_lane`` (0/1); ``has_right_lane`` (0/1);
* per slot, in ``SLOT_NAMES`` order: ``present`` (0/1); ``gap / neighbour_range`` clipped to
  [-1, 1] (an empty slot reads 1.0, "free up to the range"); ``rel_speed / speed_scale``
  clipped to [-1, 1] (0.0 for an empty slot); ``near_gap / near_gap_range`` clipped to [-1, 1]
  (1.0 for an empty slot), where ``near_gap = min(gap, gap in near_gap_horizon seconds)`` and the
  gap in ``h`` seconds, both keeping their speeds, is ``gap + rel_speed * h`` for a leader and
  ``gap - rel_speed * h`` for a follower (``near_gap = gap`` when ``h = 0``);
* with ``required_decel_scale = b > 0``, one more entry per slot, in ``SLOT_NAMES`` order after
  the slot blocks: the constant deceleration that keeps the gap to that neighbour from closing,
  ``closing speed^2 / (2 * gap) / b`` clipped to [0, 1], where the closing speed is
  ``-rel_speed`` for a leader (the ego is faster) and ``rel_speed`` for a follower; 0.0 when the
  gap opens or holds (or the slot is empty), 1.0 when the gap is <= 0 (an overlap).
* with ``goal_distance_scale = d > 0``, one last entry: the ego row's ``gap`` / d clipped to [0, 1].
  Scenario files with a goal edge (an exit) put the distance from the ego to the diverge there (the
  ego row's gap is 0 otherwise): without it the urgency of the exit is not observable.

Beyond points (``info["beyond_points"]``, in process only: not in the ``state`` message)
--------------------------------------------------------------------------------------
A float64 array of shape ``(len(BEYOND_NAMES), len(POINT_FIELDS))``, rows as the neighbour rows
above (``slot`` = ``1 + len(SLOT_NAMES) + i``): the nearest vehicle ahead / behind on the lane *two*
to the left and two to the right, within the neighbour range. Such a car may change into the lane
between it and the ego in the same step as the ego (docs/safety.md, "The exit scenario", cause C);
the RSS shield's ``beyond_lane`` check reads it. The observation vector does not encode it.

The present flag keeps "empty" distinguishable from "a vehicle exactly at the range". The second,
short-range gap channel gives the network resolution where a lane change is decided: whether the
target-lane follower overlaps the ego by half a metre (a collision) or leaves a metre free (safe)
is 0.05 apart in ``gap / 30 m`` but 0.3 apart in ``gap / 5 m``. On the tuning seeds it cut the
greedy DQN's caused collisions on the ring from 3-13% to 1-1.3% (docs/design.md).
With ``near_gap_horizon = h > 0`` the channel reads the gap the vehicles will have ``h`` seconds
later when that is smaller than the gap now: with h = 0.5 s (one decision interval on the shipped
configs) a leader 0.8 m ahead but 3.7 m/s slower reads as an overlap, as it is one for a lane
change. The default, 0, reads the gap now (urban.yaml uses it). config/ring.yaml uses h = 1 s (the
gap rule's headway until its re-tuning on 2026-12-05): on 6,000 tuning situations per run it cut
the ring DQN's caused collisions from 95 to 55 in 60,000 episodes and raised its success
(research/tuning/ring_dqn.md, section "2026-12-05, third session"); judged on 1,800 situations per
run, 0.5 s had shown no effect, too few to tell.

The required-deceleration block is the safety quantity of gap-acceptance models such as MOBIL
(Kesting, Treiber and Helbing 2007): how hard the ego must brake behind its new leader, or its new
follower behind it, for a lane change to stay collision-free. On the ring it separates the outcome
of a commanded change nearly in one threshold -- below ~6 m/s^2 almost every change succeeds,
above ~8 m/s^2 almost every change collides (research/tuning/ring_dqn.md, tenth session) -- where
in (gap, rel_speed) the boundary is a curve the network must learn from the few changes tried near
it: a leader 0.84 m ahead and 3.7 m/s slower needs 8.1 m/s^2 (collides), one 3.4 m ahead and
8 m/s slower 9.4 m/s^2 (collides), one 3 m ahead and 3.7 m/s slower 2.3 m/s^2 (safe).
The default, 0, leaves the block out, and every shipped config does: with it (scale 9 m/s^2) the
ring's DQN caused more collisions on its tuning seeds, not fewer (12 against 2 on seeds 100-104,
research/tuning/ring_dqn.md, tenth session).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from der_ros.configuration import ConfigError, param

__all__ = [
    "POINT_FIELDS",
    "SLOT_NAMES",
    "BEYOND_NAMES",
    "EGO_FEATURES",
    "SLOT_FEATURES",
    "ObservationConfig",
    "field_index",
    "empty_points",
    "empty_beyond_points",
    "encode_observation",
    "encode_point_rows",
    "observation_size",
    "observation_space",
]

#: Column names of ``info["points"]`` (and FLOAT64 fields of the ``state`` PointCloud2), in order.
POINT_FIELDS: tuple[str, ...] = (
    "x",
    "y",
    "z",
    "speed",
    "rel_speed",
    "gap",
    "lane",
    "target_lane",
    "present",
    "slot",
    "lane_count",
    "length",
)

#: Neighbour slots (rows 1.. of the points), in order.
SLOT_NAMES: tuple[str, ...] = (
    "leader",
    "follower",
    "left_leader",
    "left_follower",
    "right_leader",
    "right_follower",
)

#: Rows of ``info["beyond_points"]``: the nearest vehicles two lanes to the left and to the right, in order.
BEYOND_NAMES: tuple[str, ...] = ("left2_leader", "left2_follower", "right2_leader", "right2_follower")

#: Names of the ego part of the observation vector.
EGO_FEATURES: tuple[str, ...] = ("speed", "lane", "target_direction", "has_left_lane", "has_right_lane")
#: Names of the per-slot part of the observation vector.
SLOT_FEATURES: tuple[str, ...] = ("present", "gap", "rel_speed", "near_gap")

_COL = {name: i for i, name in enumerate(POINT_FIELDS)}
_SPEED, _REL, _GAP, _LANE = _COL["speed"], _COL["rel_speed"], _COL["gap"], _COL["lane"]
_TARGET, _PRESENT, _LANES = _COL["target_lane"], _COL["present"], _COL["lane_count"]
#: Per slot: a leader (ahead of the ego: its gap grows with its relative speed) or a follower.
_IS_LEADER: tuple[bool, ...] = tuple(name.endswith("leader") for name in SLOT_NAMES)


def field_index(name: str) -> int:
    """Column index of a point field (``KeyError`` names the valid fields)."""
    try:
        return _COL[name]
    except KeyError:
        raise KeyError(f"unknown point field {name!r}; fields are {', '.join(POINT_FIELDS)}") from None


@dataclass
class ObservationConfig:
    """How points are normalised into the observation vector (section 5.1: 30 m neighbourhood)."""

    neighbour_range: float = param(
        30.0, "neighbour range in metres: neighbours farther than this gap are not observed (paper: 30 m)", low=1.0
    )
    speed_scale: float = param(20.0, "speed (m/s) that maps to 1.0 in the observation", low=0.1)
    max_lanes: int = param(3, "largest lane count of the network, for normalising the lane index", low=2, high=16)
    near_gap_range: float = param(
        5.0,
        "gap in metres that maps to 1.0 in the second, short-range gap channel (resolution where a lane "
        "change is decided: a small overlap vs. a small free gap)",
        low=0.1,
    )
    near_gap_horizon: float = param(
        0.0,
        "seconds of look-ahead of the short-range gap channel: it reads min(gap now, gap after this long "
        "at constant speeds), so a closing neighbour reads nearer; 0 reads the gap now",
        low=0.0,
        high=10.0,
    )

    required_decel_scale: float = param(
        0.0,
        "deceleration in m/s^2 that maps to 1.0 in the required-deceleration block (closing speed^2 / "
        "(2 gap) per neighbour slot, 1.0 for an overlap; SUMO's emergency braking of a passenger car is "
        "9 m/s^2); 0 leaves the block out of the observation",
        low=0.0,
        high=100.0,
    )
    goal_distance_scale: float = param(
        0.0,
        "metres that map to 1.0 in the goal-distance entry (scenario files with a goal edge: the distance "
        "from the ego to the diverge, carried in the ego row's gap field; the exit scenario uses 300); "
        "0 leaves the entry out of the observation",
        low=0.0,
        high=100_000.0,
    )

    def check(self) -> None:
        for name in ("neighbour_range", "near_gap_range", "near_gap_horizon", "required_decel_scale",
                     "goal_distance_scale"):  # fmt: skip
            if not np.isfinite(getattr(self, name)):
                raise ConfigError(f"{name} = {getattr(self, name)!r}, expected a finite number")


def empty_points() -> np.ndarray:
    """Points with every neighbour slot empty (row 0 zeroed; the caller fills the ego)."""
    pts = np.zeros((1 + len(SLOT_NAMES), len(POINT_FIELDS)), dtype=np.float64)
    pts[:, _COL["slot"]] = np.arange(1 + len(SLOT_NAMES), dtype=np.float64)
    pts[1:, _COL["lane"]] = -1.0
    pts[1:, _COL["target_lane"]] = -1.0
    pts[0, _COL["present"]] = 1.0
    return pts


def empty_beyond_points() -> np.ndarray:
    """Beyond points (``BEYOND_NAMES`` rows) with every slot empty."""
    pts = np.zeros((len(BEYOND_NAMES), len(POINT_FIELDS)), dtype=np.float64)
    pts[:, _COL["slot"]] = np.arange(1 + len(SLOT_NAMES), 1 + len(SLOT_NAMES) + len(BEYOND_NAMES), dtype=np.float64)
    pts[:, _COL["lane"]] = -1.0
    pts[:, _COL["target_lane"]] = -1.0
    return pts


def observation_size(cfg: ObservationConfig | None = None) -> int:
    """Length of the observation vector (``cfg`` None: the defaults, without the deceleration block)."""
    n = len(EGO_FEATURES) + len(SLOT_FEATURES) * len(SLOT_NAMES)
    if cfg is not None and cfg.required_decel_scale > 0.0:
        n += len(SLOT_NAMES)
    if cfg is not None and cfg.goal_distance_scale > 0.0:
        n += 1
    return n


def observation_space(cfg: ObservationConfig) -> gym.spaces.Box:
    """The gymnasium space of :func:`encode_observation`'s output (every entry in [-1, 1])."""
    return gym.spaces.Box(low=-1.0, high=1.0, shape=(observation_size(cfg),), dtype=np.float32)


def encode_observation(points: np.ndarray, cfg: ObservationConfig) -> np.ndarray:
    """The float32 observation vector of a points array (see the module docstring).

    Pure and deterministic, so the env (in process) and the agent node (after a PointCloud2
    round trip of the float64 points) compute bit-identical observations.
    """
    pts = np.asarray(points, dtype=np.float64)
    expected = (1 + len(SLOT_NAMES), len(POINT_FIELDS))
    if pts.shape != expected:
        raise ValueError(f"points have shape {pts.shape}, expected {expected} (rows: ego + {SLOT_NAMES})")
    return encode_point_rows(pts.tolist(), cfg)


def encode_point_rows(rows: list[list[float]], cfg: ObservationConfig) -> np.ndarray:
    """:func:`encode_observation` of points given as nested lists of floats (no shape check).

    The environment builds its points as lists and encodes them here before converting them
    to an array, which saves the array round trip on its hot path; both routes run this same
    arithmetic on the same float values, so they give bit-identical observations.
    """
    # Plain float arithmetic on lists: several times faster than numpy ops on arrays this small,
    # and every operation is IEEE-exact the same way in the env and in the agent node. The
    # conditional expressions compute exactly ``min(max(x, lo), hi)`` (the same comparisons,
    # NaN and signed zeros included) without the builtin calls, which dominate at this size.
    ego = rows[0]
    lane = ego[_LANE]
    speed_scale, rng, near, h = cfg.speed_scale, cfg.neighbour_range, cfg.near_gap_range, cfg.near_gap_horizon
    v = ego[_SPEED] / speed_scale
    m = 0.0 if 0.0 > v else v
    out = [1.0 if 1.0 < m else m]
    v = lane / (cfg.max_lanes - 1)
    m = 0.0 if 0.0 > v else v
    out.append(1.0 if 1.0 < m else m)
    v = ego[_TARGET] - lane
    m = -1.0 if -1.0 > v else v
    out.append(1.0 if 1.0 < m else m)
    out.append(1.0 if lane < ego[_LANES] - 1 else 0.0)
    out.append(1.0 if lane > 0 else 0.0)
    for row, leads in zip(rows[1:], _IS_LEADER):
        if row[_PRESENT] > 0.5:
            gap = row[_GAP]
            g = gap / rng
            g = -1.0 if -1.0 > g else g
            r = row[_REL] / speed_scale
            r = -1.0 if -1.0 > r else r
            if h > 0.0:
                later = gap + row[_REL] * h if leads else gap - row[_REL] * h
                gap = later if later < gap else gap
            n = gap / near
            n = -1.0 if -1.0 > n else n
            out += (1.0, 1.0 if 1.0 < g else g, 1.0 if 1.0 < r else r, 1.0 if 1.0 < n else n)
        else:
            out += (0.0, 1.0, 0.0, 1.0)
    b = cfg.required_decel_scale
    if b > 0.0:
        for row, leads in zip(rows[1:], _IS_LEADER):
            if row[_PRESENT] > 0.5:
                gap = row[_GAP]
                closing = -row[_REL] if leads else row[_REL]
                if gap <= 0.0:
                    out.append(1.0)
                elif closing > 0.0:
                    d = closing * closing / (2.0 * gap) / b
                    out.append(1.0 if d > 1.0 else d)
                else:
                    out.append(0.0)
            else:
                out.append(0.0)
    if cfg.goal_distance_scale > 0.0:  # the ego row's gap: metres to the diverge (scenario files with a goal edge)
        v = ego[_GAP] / cfg.goal_distance_scale
        m = 0.0 if 0.0 > v else v
        out.append(1.0 if 1.0 < m else m)
    return np.array(out, dtype=np.float32)
