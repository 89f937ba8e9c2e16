"""The traffic scene of a running simulation, for viewers: every vehicle and the road (ROS-free).

The observation holds the ego and six neighbour slots *relative to the ego*; a person watching
an episode wants the whole scene in world coordinates. This module is the core of the bridge's
``scene/vehicles`` and ``scene/road`` marker topics: the bridge node and the offline tools turn a
:class:`Scene` into the contract's CDR bytes (:mod:`der_ros.contract.scene`), reading the values
from here.

Where the poses come from: on traci a getter per vehicle is a round trip, so
:class:`~sumo_bridge.lane_change_env.LaneChangeEnv` subscribes every vehicle to :data:`SCENE_VARS`
(instead of the speed alone, which the reward reads) and the whole scene comes with the one
``getAllSubscriptionResults`` call per step the env makes anyway. But SUMO evaluates subscriptions
at every simulation step, five per decision, about 1 us per variable and vehicle (ring, 28
vehicles, shared 2-core machine: 350 us per simulation step with the speed alone, 379 us with
position and angle), while the scene is read once per decision; on libsumo, where a getter is an
in-process call, the env therefore reads position and angle with getters in ``scene()`` and builds
the same mapping (``bench/graph.py``'s ``scene_*`` figures). Either way only the viewers pay: the
bridge enables the scene with its ``markers`` parameter, training never does. The sizes, which
never change, are asked once per vehicle (the ``size`` callback).

Vehicles keep their marker id for as long as they exist (:class:`SceneTracker`: a viewer
interpolates and trails by id); a vehicle that left gets a DELETE (its id in
:attr:`Scene.removed`) and is never given the id again.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from math import cos, sin
from typing import Any

import numpy as np

from der_ros.contract import EGO_ROLE, SCENE_ROLES, TRAFFIC_ROLE, LaneLine, VehicleMarker
from sumo_bridge.observation import SLOT_NAMES
from sumo_bridge.sim_backend import constants

__all__ = ["SCENE_VARS", "Scene", "SceneTracker", "read_lanes"]

_tc = constants()
_V_SPEED, _V_POS, _V_ANGLE = _tc.VAR_SPEED, _tc.VAR_POSITION, _tc.VAR_ANGLE
_RAD = math.pi / 180.0
#: per-vehicle subscription of an env with the scene enabled (speed first: the reward reads it)
SCENE_VARS: list[int] = [_V_SPEED, _V_POS, _V_ANGLE]
# the contract's roles are the ego, the observation's slots in order, and traffic
assert SCENE_ROLES == (EGO_ROLE, *SLOT_NAMES, TRAFFIC_ROLE)


@dataclass(frozen=True)
class Scene:
    """Every vehicle in the simulation at one step, and the vehicles gone since the previous scene.

    A vehicle is given as the cube a viewer draws (:class:`der_ros.contract.VehicleMarker`): SUMO
    id, stable marker id, role, the middle of the vehicle (SUMO's position is the middle of the
    front bumper: half a length further along the heading), heading as REP 103 yaw (SUMO's angle
    is degrees clockwise from north: ``yaw = radians(90 - angle)``), length and width.
    """

    vehicles: tuple[VehicleMarker, ...]
    #: marker ids of the vehicles that left since the previous scene (DELETE markers)
    removed: tuple[int, ...]


class SceneTracker:
    """Builds :class:`Scene` s from the env's subscription results; owns the stable marker ids and
    the vehicles' sizes (``size(vehicle_id) -> (length, width)``, asked once per vehicle)."""

    def __init__(self, size: Callable[[str], tuple[float, float]]) -> None:
        self._size = size
        self._ids: dict[str, int] = {}
        self._sizes: dict[str, tuple[float, float]] = {}
        self._next_id = 0

    def forget_sizes(self) -> None:
        """After a reload the same ids may name vehicles of another type: ask their sizes again."""
        self._sizes.clear()

    def update(self, results: Mapping[str, Mapping[int, Any]], ego_id: str,
               slots: Mapping[str, str | None]) -> Scene:  # fmt: skip
        """The scene from ``getAllSubscriptionResults()`` (vehicles subscribed to :data:`SCENE_VARS`).

        ``slots`` maps each neighbour slot name to the id of the vehicle in it (the env's
        ``neighbour_ids()``). Vehicles subscribed to fewer variables (before the scene was
        enabled) are skipped.
        """
        roles = {vid: slot for slot, vid in slots.items() if vid is not None}
        roles[ego_id] = EGO_ROLE
        ids, sizes = self._ids, self._sizes
        vehicles = []
        for vid, var in results.items():
            if _V_POS not in var:
                continue
            mid = ids.get(vid)
            if mid is None:
                mid = ids[vid] = self._next_id
                self._next_id += 1
            size = sizes.get(vid)
            if size is None:
                size = sizes[vid] = self._size(vid)
            x, y = var[_V_POS]
            yaw = _RAD * (90.0 - var[_V_ANGLE])
            half = 0.5 * size[0]
            vehicles.append(VehicleMarker(mid, vid, roles.get(vid, TRAFFIC_ROLE), x - half * cos(yaw),
                                          y - half * sin(yaw), yaw, size[0], size[1]))  # fmt: skip
        removed: tuple[int, ...] = ()
        if len(ids) > len(vehicles):
            present = {v.vehicle_id for v in vehicles}
            gone = [vid for vid in ids if vid not in present]
            removed = tuple(ids.pop(vid) for vid in gone)
            for vid in gone:
                sizes.pop(vid, None)
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
