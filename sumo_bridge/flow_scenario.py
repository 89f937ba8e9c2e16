"""Set-up, goal and speed actions of scenarios read from a file (:mod:`sumo_bridge.scenario_file`).

A mixin of :class:`~sumo_bridge.lane_change_env.LaneChangeEnv` (which keeps the stepping, the
reward and the observation reading): everything here runs only when ``ScenarioConfig.file`` is set.

Traffic and resets
------------------
The background traffic comes from the scenario's demand files (flows) and keeps running between
episodes. ``reset(seed=s)`` reloads the simulation with SUMO seed drawn from ``s`` and puts back the
*warmed state* of that traffic seed: ``warmup_seconds`` of traffic saved once with SUMO's random
number state (``--save-state.rng``) under ``<network build>/states/<seed>_w<warm-up>_dt<step>_f.xml`` by a
fresh process (:mod:`sumo_bridge.traffic_state`: the file does not depend on what ran before), so the
first seeded reset of a traffic seed costs a Python start and the warm-up (~1.5 s for the exit scenario)
and every later one a ``load`` + ``loadState``; a seeded reset is a pure function of ``s``. A reset without a seed keeps the
traffic running: the last ego is removed, ``ego_gap_seconds`` of traffic run, and the next ego is
taken over -- no network reload (see bench/README.md for the times).

The ego is *taken over*, not inserted: a passenger car already driving on the start lane of
``ego.route[0]`` inside ``ego.depart_pos`` (chosen with the env's RNG) gets the ego's vType, speed
factor 1, the ego's route and laneChangeMode, and a fresh id per episode is its own. Inserting a
new vehicle into a saturated lane needs a gap SUMO deems safe for the follower, which dense
motorway traffic (~27 m gaps at 25 m/s) does not leave: SUMO then delays the insertion for 5-17 s
(``../shared/notes/sumo.md``).

Goal edge and 'missed'
----------------------
Success: the ego is on the goal edge (an exit ramp). Missed, as a driver would define it: the ego
has halted (speed < ``halt_speed``) for ``halt_seconds`` within ``miss_zone`` metres of the diverge
on a lane that does not lead to the goal -- i.e. it arrived at the split on the wrong lane, or
stopped on the motorway to wait for a gap (SUMO's own vehicles wait at the lane end; on a real
road that is a failure). It terminates the episode with ``reward_missed``. Halting is sampled at
the end of each decision.

Speed actions
-------------
``faster`` / ``slower`` move the ego's target speed by ``speed_step`` from its current target
(or, first, its current speed), clipped to [0, the lane's speed limit]. The target is the ego's
*maximum speed* (``vehicle.setMaxSpeed``), so the ego stays under its own car-following model: it
accelerates at most at ``accel``, slows to a lower target at ``decel`` (4.5 m/s^2 for the exit's
ego), and when its safe speed asks for more -- a car standing ahead after a lane change -- it brakes
up to its ``emergencyDecel`` (9), as every SUMO car does and as the shield's ``brake_min`` assumes.
Its dawdling is switched off with the first speed action (``vehicle.setImperfection(0)``): a
commanded target speed is held, not dawdled below. Not ``vehicle.setSpeed``: a TraCI speed command
with SUMO's default speed mode (31) "regards the maximum deceleration", i.e. never brakes harder
than ``decel`` even when the safe speed needs it (``MSVehicle::Influencer::influenceSpeed`` floors
the speed at ``minNextSpeed``), and with that bit cleared it brakes without any bound; the exit
table's shielded agents ran into cars standing at the split that way (docs/safety.md, "The
own-lane leader").
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from sumo_bridge.scenario import lane_change_params
from sumo_bridge.scenario_file import ScenarioSpec
from sumo_bridge.traffic_state import save_warm_state

log = logging.getLogger(__name__)

__all__ = ["FlowScenarioMixin"]


class FlowScenarioMixin:
    """Reset, goal and speed actions of file scenarios (mixed into LaneChangeEnv)."""

    _spec: ScenarioSpec | None
    api: Any
    config: Any

    # ------------------------------------------------------------------ reset
    def _reset_file(self) -> None:
        spec, api = self._spec, self.api
        assert spec is not None
        if self._need_load:
            self._load_warm_state()
            self._ego_serial = 0
        elif self.ego_id in api.vehicle.getIDList():
            api.vehicle.unsubscribeContext(self.ego_id, self._tc.CMD_GET_VEHICLE_VARIABLE, self._ctx_range)
            api.vehicle.unsubscribe(self.ego_id)
            api.vehicle.remove(self.ego_id)
        self._ego_present = False
        self._episodes_since_load += 1
        self._warmup(spec.traffic.ego_gap_seconds)
        self._halted_s = 0.0
        self._target_speed = None
        for _attempt in range(self._steps(30.0)):  # one SUMO step at a time until a car is in the window
            if self._take_over_ego():
                return
            self._sim_step()
        raise RuntimeError(f"{spec.path}: no passenger car on {spec.ego.route[0]}_{spec.ego.lane} within "
                           f"ego.depart_pos {list(spec.ego.depart_pos)} in 30 s of traffic (demand too light?)")  # fmt: skip

    def _state_file(self, sumo_seed: int) -> Path:
        # the network directory is keyed by the sources and demand; the warm-up and the step are in the name
        assert self._spec is not None
        warm, dt = self._spec.traffic.warmup_seconds, self.config.step_length
        # "_f": made by a fresh process (states saved in-process before 2026-12-07 are not reused)
        return Path(self.network.directory) / "states" / f"{sumo_seed}_w{warm:g}_dt{dt:g}_f.xml"

    def _load_warm_state(self) -> None:
        """Load (a fresh SUMO seed from the env's RNG) and put back that seed's warmed traffic."""
        spec, api = self._spec, self.api
        assert spec is not None and self._rng is not None
        sumo_seed = int(self._rng.integers(0, 2**31 - 1))
        state = self._state_file(sumo_seed)
        if not state.is_file():  # made by a fresh process, so that it is the same wherever it is made
            save_warm_state(self._sumo_args(sumo_seed, gui=False), self._steps(spec.traffic.warmup_seconds), state)
        self.sim.load(self._sumo_args(sumo_seed))
        if not self._offsets:
            self._build_corridor()
        api.simulation.loadState(str(state))
        api.simulation.subscribe([self._v_departed, self._v_colliding])  # loadState drops subscriptions
        for vid in api.vehicle.getIDList():  # loaded vehicles do not 'depart': subscribe them here
            api.vehicle.subscribe(vid, self._vehicle_vars)
        if self._scene is not None:
            self._scene.forget_sizes()
        self._episodes_since_load = 0
        self._need_load = False

    def _take_over_ego(self) -> bool:
        """Make a passenger car on the start lane inside the depart window the ego; False if none is there."""
        spec, api, rng, cfg = self._spec, self.api, self._rng, self.config
        assert spec is not None and rng is not None
        lo, hi = spec.ego.depart_pos
        lane_id = f"{spec.ego.route[0]}_{spec.ego.lane}"
        cands = sorted(v for v in api.lane.getLastStepVehicleIDs(lane_id)
                       if lo <= api.vehicle.getLanePosition(v) <= hi and api.vehicle.getVehicleClass(v) == "passenger")  # fmt: skip
        if not cands:
            return False
        self.ego_id = cands[int(rng.integers(len(cands)))]
        api.vehicle.setType(self.ego_id, cfg.ego_type or spec.ego.type)
        for name, value in lane_change_params(cfg.ego_lane_change_params).items():  # e.g. the sumo_tuned baseline's
            api.vehicle.setParameter(self.ego_id, f"laneChangeModel.{name}", repr(value))
        api.vehicle.setSpeedFactor(self.ego_id, 1.0)
        api.vehicle.setRoute(self.ego_id, list(spec.ego.route))
        api.vehicle.setLaneChangeMode(self.ego_id, cfg.ego_lane_change_mode)
        self._subscribe_ego()
        return True

    # ------------------------------------------------------------------ goal
    def _edge_goal(self) -> tuple[float, bool, str | None]:
        """(reward, terminated, event) of the goal edge after a decision (see the module docstring)."""
        spec, cfg = self._spec, self.config
        assert spec is not None and spec.goal.edge is not None
        road, pos, speed = self._ego_road_pos_speed
        if road == spec.goal.edge:
            self._target_reached = True
            return cfg.reward_success, cfg.success_ends_episode, ("success" if cfg.success_ends_episode else None)
        diverge = spec.ego.route[spec.ego.route.index(spec.goal.edge) - 1]
        if (road == diverge and self._ego_lane not in spec.goal.lanes and speed < spec.traffic.halt_speed
                and pos >= self._edge_length(diverge) - spec.traffic.miss_zone):  # fmt: skip
            self._halted_s += self.step_seconds
            if self._halted_s >= spec.traffic.halt_seconds - 1e-9:
                return cfg.reward_missed, True, "missed"
        else:
            self._halted_s = 0.0
        return 0.0, False, None

    def _goal_distance(self, road: str, pos: float) -> float:
        """Metres from the ego to the diverge (the end of the route edge before the goal edge); 0 past it.
        Observed as the ego row's gap (ObservationConfig.goal_distance_scale)."""
        spec = self._spec
        assert spec is not None and spec.goal.edge is not None
        route = spec.ego.route
        k = route.index(spec.goal.edge)
        if road not in route[:k]:
            return 0.0
        i = route.index(road)
        return max(self._edge_length(road) - pos, 0.0) + sum(self._edge_length(e) for e in route[i + 1:k])

    def _edge_length(self, edge: str) -> float:
        length = self._edge_lengths.get(edge)
        if length is None:
            length = self._edge_lengths[edge] = float(self.api.lane.getLength(f"{edge}_0"))
        return length

    # ------------------------------------------------------------------ speed actions
    def _speed_action(self, a: int) -> None:
        """3 = faster, 4 = slower: step the ego's target speed, its maximum speed (see the module docstring:
        SUMO's car-following keeps it safe, with emergency braking)."""
        api, ego = self.api, self.ego_id
        if self._target_speed is None:  # the first speed action of this ego: its own limits, then no dawdling
            self._ego_top_speed = float(api.vehicle.getMaxSpeed(ego))
            api.vehicle.setImperfection(ego, 0.0)
        base = self._target_speed if self._target_speed is not None else self._ego_road_pos_speed[2]
        # the lane's limit for this ego (getAllowedSpeed would return the target set last)
        limit = min(float(api.lane.getMaxSpeed(api.vehicle.getLaneID(ego))) * float(api.vehicle.getSpeedFactor(ego)),
                    self._ego_top_speed)  # fmt: skip
        step = self.config.speed_step if a == 3 else -self.config.speed_step
        self._target_speed = min(max(base + step, 0.0), limit)
        api.vehicle.setMaxSpeed(ego, self._target_speed)
