"""The traffic scene of a running simulation, for viewers: every vehicle and the road (ROS-free).

The observation holds the ego and six neighbour slots *relative to the ego*; a person watching
an episode wants the whole scene in world coordinates. This module is the core of the bridge's
``scene/vehicles`` and ``scene/road`` marker topics (:mod:`der_ros.contract`): the bridge node
converts a :class:`Scene` to rclpy messages (:mod:`der_ros.nodes.msg_conversions`), offline tools
to rosbags messages (:mod:`der_ros.bag.messages`), and both read the values from here.

Why subscriptions: reading every vehicle's position with a getter per vehicle costs one call
(one round trip on traci) per vehicle per step. :class:`~sumo_bridge.lane_change_env.LaneChangeEnv`
already subscribes each departing vehicle to its speed (the reward's mean speed); with the scene
enabled it subscribes :data:`SCENE_VARS` instead, so the whole scene comes with the one
``getAllSubscriptionResults`` call per step the env makes anyway. Only the viewers pay for it:
the bridge enables it with its ``markers`` parameter, training never does.

Vehicles keep their marker id for as long as they exist (:class:`SceneTracker`: a viewer
interpolates and trails by id); a vehicle that left gets a DELETE (its id in
:attr:`Scene.removed`) and is never given the id again.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from der_ros.contract import SCENE_ROLES, TRAFFIC_ROLE, LaneLine, VehicleMarker
from sumo_bridge.observation import SLOT_NAMES
from sumo_bridge.sim_backend import constants

__all__ = ["SCENE_VARS", "Vehicle", "Scene", "SceneTracker", "read_lanes"]

_tc = constants()
_V_SPEED, _V_POS, _V_ANGLE, _V_LENGTH, _V_WIDTH = (_tc.VAR_SPEED, _tc.VAR_POSITION, _tc.VAR_ANGLE, _tc.VAR_LENGTH,
                                                   _tc.VAR_WIDTH)  # fmt: skip
#: per-vehicle subscription of an env with the scene enabled (speed first: the reward reads it)
SCENE_VARS: list[int] = [_V_SPEED, _V_POS, _V_ANGLE, _V_LENGTH, _V_WIDTH]
# the contract's roles are the ego, the observation's slots in order, and traffic
assert SCENE_ROLES == ("ego", *SLOT_NAMES, TRAFFIC_ROLE)


class Vehicle(NamedTuple):
    """One vehicle as SUMO reports it, with its role and stable marker id (a NamedTuple: the bridge
    builds one per vehicle per step)."""

    id: str
    marker_id: int
    #: ``ego``, a neighbour slot name or ``traffic`` (:data:`der_ros.contract.SCENE_ROLES`)
    role: str
    #: SUMO's position: the middle of the front bumper, m
    x: float
    y: float
    #: SUMO's angle: degrees clockwise from north
    angle: float
    length: float
    width: float

    @property
    def yaw(self) -> float:
        """Heading in radians counter-clockwise from the x axis (REP 103): ``radians(90 - angle)``."""
        return math.radians(90.0 - self.angle)

    def marker(self) -> VehicleMarker:
        """The vehicle as a cube marker: centred half a length behind the front bumper."""
        yaw = math.radians(90.0 - self.angle)
        half = 0.5 * self.length
        return VehicleMarker(self.marker_id, self.id, self.role, self.x - half * math.cos(yaw),
                             self.y - half * math.sin(yaw), yaw, self.length, self.width)  # fmt: skip


@dataclass(frozen=True)
class Scene:
    """Every vehicle in the simulation at one step, and the vehicles gone since the previous scene."""

    vehicles: tuple[Vehicle, ...]
    #: marker ids of the vehicles that left since the previous scene (DELETE markers)
    removed: tuple[int, ...]

    def by_id(self) -> dict[str, Vehicle]:
        return {v.id: v for v in self.vehicles}

    def markers(self) -> list[VehicleMarker]:
        return [v.marker() for v in self.vehicles]


class SceneTracker:
    """Builds :class:`Scene` s from the env's subscription results; owns the stable marker ids."""

    def __init__(self) -> None:
        self._ids: dict[str, int] = {}
        self._next_id = 0

    def update(self, results: Mapping[str, Mapping[int, Any]], ego_id: str,
               slots: Mapping[str, str | None]) -> Scene:  # fmt: skip
        """The scene from ``getAllSubscriptionResults()`` (vehicles subscribed to :data:`SCENE_VARS`).

        ``slots`` maps each neighbour slot name to the id of the vehicle in it (the env's
        ``neighbour_ids()``). Vehicles subscribed to fewer variables (before the scene was
        enabled) are skipped.
        """
        roles = {vid: slot for slot, vid in slots.items() if vid is not None}
        roles[ego_id] = "ego"
        ids = self._ids
        vehicles = []
        for vid, var in results.items():
            if _V_POS not in var:
                continue
            mid = ids.get(vid)
            if mid is None:
                mid = ids[vid] = self._next_id
                self._next_id += 1
            x, y = var[_V_POS]
            vehicles.append(Vehicle(vid, mid, roles.get(vid, TRAFFIC_ROLE), float(x), float(y), float(var[_V_ANGLE]),
                                    float(var[_V_LENGTH]), float(var[_V_WIDTH])))  # fmt: skip
        removed: tuple[int, ...] = ()
        if len(ids) > len(vehicles):
            present = {v.id for v in vehicles}
            gone = [vid for vid in ids if vid not in present]
            removed = tuple(ids.pop(vid) for vid in gone)
        return Scene(tuple(vehicles), removed)


def read_lanes(api: Any) -> tuple[LaneLine, ...]:
    """Every lane of the loaded network (junction-internal lanes included: they close the road at
    junctions), sorted by id, with its centre line and width as SUMO gives them."""
    lanes = []
    for lane_id in sorted(api.lane.getIDList()):
        shape = np.asarray(api.lane.getShape(lane_id), dtype=np.float64).reshape(-1, 2)
        if len(shape) >= 2:
            lanes.append(LaneLine(lane_id, shape, float(api.lane.getWidth(lane_id))))
    return tuple(lanes)
