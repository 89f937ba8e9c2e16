"""The ring's warm traffic state: recorded after a full build, put back in place for later resets.

Why
---
A full ring reset (``simulation.load`` + placing 22-32 vehicles at standstill + a 5 s warm-up)
costs 8-14 ms, most of it the 51 SUMO steps and the load; a training stream resets every ~20
decisions, so that was ~40% of a training run's time (issue 11). Keeping the traffic running
between episodes and only replacing the ego (what the urban network does) is cheap but changes
the task: background vehicles change lanes, and within one 20 s episode the ring's two lanes
equalise (7-11 / 15-21 vehicles become ~14 / 14), so the ego would start next to a sparse, fast
inner lane instead of a dense, slow one (measured: KS statistics 0.3-0.7 on the neighbour
speeds and gaps, see :mod:`sumo_bridge.lane_change_env`).

What
----
:meth:`WarmState.record` reads, at the end of a full build's warm-up (one simulation step
before its first observation), every vehicle's lane, lane position, speed and acceleration (and
the lane-change state below). :meth:`WarmState.apply` moves the same vehicles (they are all
still in the simulation) back to those positions with ``vehicle.moveTo`` and
``vehicle.setPreviousSpeed`` (a few microseconds per vehicle; moveTo recomputes its best lanes) -- with one change: every lane
other than the ego's is rotated around the ring by a fresh offset. The placement rule of a
build draws each lane's offset independently and uniformly, so a rotated inner lane is exactly
as likely as the recorded one; the neighbour slots on the target lane are new in every
episode, while the ego's own lane repeats the build's. The caller then runs one simulation
step, as the build did after its warm-up, so the first observation comes out of SUMO's own
step (and every subscription result is renewed).

The lane-change model (LC2013) keeps urges that build up over time. Measured with a keep-lane
ego over 300 re-placements of unrotated builds (50-step episodes): re-placed right after the build,
the background vehicles changed lanes 8.56 times per episode (return 116.47); re-placed after
20 s of traffic, with the urges left as they were then, 7.82 times (116.08). SUMO 1.28 exposes
four urges as ``laneChangeModel.*`` parameters; putting back ``keepRightProbability`` gave 8.06
(116.34), the others (``speedGainProbabilityLeft`` / ``Right``: 8.00 (116.10),
``lookAheadSpeed``: 7.82 (116.08); all four: 8.22 (116.35)) nothing beyond noise for 84 more
``setParameter`` calls (~0.1 ms) per reset, so only the first is put back.

Not restored: SUMO's random number stream (it goes on; a seeded reset therefore always does a full
build, see :class:`~sumo_bridge.lane_change_env.LaneChangeEnv`), the other lane-change state
(exposed or not, e.g. the time since a vehicle's last lane change) and whatever else a vehicle
carries over, such as its route progress (refreshed when it runs low).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

__all__ = ["WarmVehicle", "WarmState"]

#: LC2013 state put back as recorded (``vehicle.getParameter`` / ``setParameter``; see the module doc)
LC_STATE_KEYS = ("laneChangeModel.keepRightProbability",)

#: Route edges used up after which a re-placed vehicle gets a fresh looping route. moveTo to an
#: edge behind the vehicle jumps to that edge's next occurrence in the route, so every episode
#: uses up to ~8 of the 36 edges of a ``loop_*`` route (one lap driven, up to one lap jumped).
ROUTE_REFRESH_INDEX = 16


class WarmVehicle(NamedTuple):
    """One vehicle of a recorded warm state."""

    vid: str
    lane: int  #: lane index
    lane_id: str  #: SUMO lane id (may be a junction's internal lane)
    pos: float  #: position of the front bumper on that lane (m)
    s: float  #: the same position as arc length around the ring (m), for rotations
    speed: float  #: m/s
    accel: float  #: m/s^2
    lc_state: tuple[str, ...]  #: values of :data:`LC_STATE_KEYS` as SUMO formats them


class WarmState:
    """Every vehicle's lane, position, speed, acceleration and lane-change urges at the end of a
    build's warm-up."""

    def __init__(self, vehicles: list[WarmVehicle], fixed_lane: int) -> None:
        self.vehicles = vehicles
        #: the lane that is put back unrotated (the ego's start lane)
        self.fixed_lane = fixed_lane

    def __len__(self) -> int:
        return len(self.vehicles)

    @classmethod
    def record(cls, api: Any, offsets: dict[str, float], fixed_lane: int) -> WarmState:
        """Read the current state of every vehicle (``offsets``: arc length of each road's start)."""
        v = api.vehicle
        vehicles = []
        for vid in v.getIDList():
            lane_id = v.getLaneID(vid)
            pos = v.getLanePosition(vid)
            s = offsets[lane_id.rsplit("_", 1)[0]] + pos
            lc_state = tuple(v.getParameter(vid, key) for key in LC_STATE_KEYS)
            speed, accel = v.getSpeed(vid), v.getAcceleration(vid)
            vehicles.append(WarmVehicle(vid, int(v.getLaneIndex(vid)), lane_id, pos, s, speed, accel, lc_state))
        return cls(vehicles, fixed_lane)

    def apply(self, api: Any, rotation: float, where: Callable[[float], tuple[str, float]]) -> None:
        """Put every vehicle back; lanes other than ``fixed_lane`` move ``rotation`` metres ahead.

        ``where(s)`` maps an arc length to ``(edge, position)`` on a normal edge (the placement
        rule of a build). The caller checks first that every recorded vehicle is still there.

        SUMO's ``moveTo`` onto the lane a vehicle is already on only overwrites its position and
        leaves the lane's vehicle list in its old order (SUMO 1.28, ``libsumo::Vehicle::moveTo``),
        so car following would then use wrong leaders: the first step collided in ~2% of such
        resets. Such a vehicle is therefore first moved to the other lane of its edge, so that
        every move removes the vehicle from one list and inserts it in order into another.
        """
        v = api.vehicle
        fixed = self.fixed_lane
        for w in self.vehicles:
            if w.lane == fixed:
                lane_id, pos = w.lane_id, w.pos
            else:
                edge, pos = where(w.s + rotation)
                lane_id = f"{edge}_{w.lane}"
            if v.getLaneID(w.vid) == lane_id:
                v.moveTo(w.vid, _other_lane(lane_id), pos)
            v.moveTo(w.vid, lane_id, pos)
            v.setPreviousSpeed(w.vid, w.speed, w.accel)
            for key, value in zip(LC_STATE_KEYS, w.lc_state):
                v.setParameter(w.vid, key, value)
            if v.getRouteIndex(w.vid) >= ROUTE_REFRESH_INDEX and lane_id[0] != ":":
                # a fresh copy of the looping route starting on the current edge (a route must
                # start where the vehicle is; skipped on a junction, done at a later reset)
                v.setRouteID(w.vid, "loop_" + lane_id.rsplit("_", 1)[0])


def _other_lane(lane_id: str) -> str:
    """The neighbouring lane of a two-lane ring edge (or junction): ``x_0`` <-> ``x_1``."""
    edge, index = lane_id.rsplit("_", 1)
    return f"{edge}_{1 - int(index)}"
