"""Set-up of the two built-in scenarios, mixed into :class:`~sumo_bridge.lane_change_env.LaneChangeEnv`.

Ring (``RingSetupMixin``): background vehicles placed at seeded positions on the closed loop, a
warm-up, and re-placements of the last build's warm traffic in between builds
(:mod:`sumo_bridge.warm_state`). Urban (``UrbanSetupMixin``): the bridge traffic keeps running and
only the ego is inserted anew. The reasons and measurements are in the env module's docstring
("Resets and determinism"). Scenario files have their own set-up (:mod:`sumo_bridge.flow_scenario`);
the env keeps the stepping, the reward and the observation reading.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from sumo_bridge.warm_state import WarmState

log = logging.getLogger(__name__)

__all__ = ["RING_EDGES", "URBAN_CORRIDOR", "RingSetupMixin", "UrbanSetupMixin"]

#: the ring's four quarter arcs, in driving order
RING_EDGES = ("bottom", "right", "top", "left")
#: the urban ego's corridor (the bridge "100" and the roads before and after it)
URBAN_CORRIDOR = ("101", "102", "100", "103", "104")


class RingSetupMixin:
    """Ring resets: builds and re-placements (see the module docstring)."""

    api: Any
    config: Any

    def _ring_where(self, s: float) -> tuple[str, float]:
        """Edge and position of arc length ``s`` on the ring, on a normal edge (the placement rule)."""
        lap = self._loop_length
        s %= lap
        for edge, off, length in self._ring_edges:
            if off <= s < off + length:
                return edge, min(s - off, length - 0.1)
        # inside a junction's internal lane: start of the next edge instead (shift < 0.3 m)
        nxt = min(((off - s) % lap, edge) for edge, off, _ in self._ring_edges)[1]
        return nxt, 0.1

    def _reset_ring(self) -> None:
        cfg = self.config
        if self._need_load or self._warm is None or self._episodes_since_load >= cfg.ring_rebuild_every:
            self._build_ring()
        elif not self._replay_ring():
            log.warning("ring: %d vehicles in the simulation, expected %d; rebuilding the traffic",
                        self.api.vehicle.getIDCount(), len(self._warm))  # fmt: skip
            self._build_ring()

    def _build_ring(self) -> None:
        """Reload, place the traffic at standstill from the seeded RNG, warm up; record the warm state."""
        cfg, api, rng = self.config, self.api, self._rng
        assert rng is not None
        self._load()
        if not self._ring_edges:
            self._ring_edges = [(e, self._offsets[e], api.lane.getLength(f"{e}_0")) for e in RING_EDGES]
        lap = self._loop_length
        where = self._ring_where
        counts = [int(rng.integers(cfg.ring_outer_vehicles[0], cfg.ring_outer_vehicles[1] + 1)),
                  int(rng.integers(cfg.ring_inner_vehicles[0], cfg.ring_inner_vehicles[1] + 1))]  # fmt: skip
        counts[cfg.ego_lane] += 1  # the ego is vehicle 0 of its lane
        for lane, n in enumerate(counts):
            if n == 0:
                continue
            free = lap - n * cfg.min_spacing
            u = np.sort(rng.uniform(0.0, free, n))
            pos = u + np.arange(n) * cfg.min_spacing + rng.uniform(0.0, lap)
            slow = rng.random(n) < cfg.slow_fraction
            for i in range(n):
                edge, p = where(float(pos[i]))
                is_ego = lane == cfg.ego_lane and i == 0
                vid = self.ego_id if is_ego else f"bg{lane}_{i}"
                vtype = "ego" if is_ego else ("slow" if slow[i] else "car")
                api.vehicle.add(vid, f"loop_{edge}", vtype, depart="now", departLane=str(lane),
                                departPos=f"{p:.3f}", departSpeed="0")  # fmt: skip
        api.vehicle.setLaneChangeMode(self.ego_id, cfg.ego_lane_change_mode)
        self._warmup(cfg.warmup_seconds, min_steps=1)
        # the state a re-placement puts back; like here, one simulation step follows it
        self._warm = None
        if cfg.ring_rebuild_every > 1:
            self._warm = WarmState.record(api, self._offsets, fixed_lane=cfg.ego_lane)
        self._subscribe_ego()
        self._episodes_since_load = 1

    def _replay_ring(self) -> bool:
        """Put the last build's warm traffic back, the other lanes rotated (:mod:`sumo_bridge.warm_state`),
        then one simulation step, as after a build's warm-up.

        False (nothing changed) if a vehicle of the recorded state has left the simulation.
        """
        api, rng, warm = self.api, self._rng, self._warm
        assert rng is not None and warm is not None
        if api.vehicle.getIDCount() != len(warm):
            return False
        warm.apply(api, float(rng.uniform(0.0, self._loop_length)), self._ring_where)
        # a lane change the agent commanded just before the last episode ended is still pending
        # (it holds for step_seconds); cancel it so the ego stays on its start lane
        api.vehicle.changeLane(self.ego_id, self.config.ego_lane, 0.0)
        # The step also renews every subscription result: right after moveTo, SUMO 1.28 answers
        # a (re)subscription partly from the previous step's positions.
        self._sim_step()
        self._episodes_since_load += 1
        return True


class UrbanSetupMixin:
    """Urban resets: the ego inserted into running bridge traffic (see the module docstring)."""

    api: Any
    config: Any

    def _reset_urban(self) -> None:
        cfg, api, rng = self.config, self.api, self._rng
        assert rng is not None
        if self._need_load or (cfg.urban_reload_every and self._episodes_since_load >= cfg.urban_reload_every):
            self._load()
            self._ego_serial = 0
            self._warmup(cfg.urban_warmup_seconds)
        elif self.ego_id in api.vehicle.getIDList():
            # drop its subscriptions first: stepping with a subscription on a removed vehicle raises
            api.vehicle.unsubscribeContext(self.ego_id, self._tc.CMD_GET_VEHICLE_VARIABLE, self._ctx_range)
            api.vehicle.unsubscribe(self.ego_id)
            api.vehicle.remove(self.ego_id)
            self._ego_present = False
        self._episodes_since_load += 1
        self._warmup(cfg.urban_ego_gap_seconds)
        if self._insert_urban_ego():
            return
        # No attempt found room. Seen about once per ~900 episodes: not a jam but a dense platoon
        # of the main northbound flow (vehicles at ~13 m/s, ~20 m apart over the whole insertion
        # window), where SUMO finds no safe insertion gap. Start over from a fresh, warmed-up
        # simulation rather than failing a long training run.
        log.warning("ego could not be inserted on the bridge after 20 attempts (dense traffic on the start lane); "
                    "reloading the simulation")  # fmt: skip
        self._load()
        self._ego_serial = 0
        self._warmup(cfg.urban_warmup_seconds)
        self._episodes_since_load = 1
        if not self._insert_urban_ego():
            raise RuntimeError(
                "could not insert the ego vehicle on the bridge after 20 attempts, even after a reload "
                "(traffic too dense? check urban_depart_pos and the background demand)"
            )

    def _insert_urban_ego(self) -> bool:
        """Try up to 20 seeded positions on the start lane; True once the ego is in the network."""
        cfg, api = self.config, self.api
        for _attempt in range(20):
            # a fresh id per attempt: SUMO 1.28 never inserts a vehicle re-added under the id of one
            # removed before its insertion; unique ids also keep logs unambiguous
            self._ego_serial += 1
            self.ego_id = f"ego.{self._ego_serial}"
            pos = self._urban_insert_pos()
            api.vehicle.add(self.ego_id, "ego_route", "ego", depart="now", departLane=str(cfg.ego_lane),
                            departPos=f"{pos:.3f}", departSpeed="max")  # fmt: skip
            api.vehicle.setLaneChangeMode(self.ego_id, cfg.ego_lane_change_mode)
            for _ in range(3):
                self._sim_step()
                if self.ego_id in api.vehicle.getIDList():
                    self._subscribe_ego()
                    return True
            api.vehicle.remove(self.ego_id)  # could not be inserted there (blocked): try elsewhere
            self._sim_step()
        return False

    def _urban_insert_pos(self) -> float:
        """A seeded position for the ego on the bridge: the middle of a random gap that fits it.

        Dense lanes rarely leave room at a uniformly drawn position, so choose among the gaps
        between the vehicles already on the start lane inside ``urban_depart_pos``.
        """
        cfg, api, rng = self.config, self.api, self._rng
        assert rng is not None
        lo, hi = cfg.urban_depart_pos
        lane_id = f"{URBAN_CORRIDOR[2]}_{cfg.ego_lane}"
        ends = sorted(
            (api.vehicle.getLanePosition(v), api.vehicle.getLength(v)) for v in api.lane.getLastStepVehicleIDs(lane_id)
        )
        fronts = [lo - 100.0] + [p for p, _ in ends] + [hi + 100.0]
        backs = [lo - 100.0] + [p - length for p, length in ends] + [hi + 100.0]
        need = 5.0 + 2 * 2.5 + 12.0  # ego length + min gaps + room for the follower to brake
        gaps = [
            (backs[i + 1] - fronts[i], 0.5 * (fronts[i] + backs[i + 1]) + 2.5)
            for i in range(len(fronts) - 1)
            if lo <= 0.5 * (fronts[i] + backs[i + 1]) <= hi
        ]
        fitting = [mid for size, mid in gaps if size >= need]
        if fitting:
            return float(fitting[int(rng.integers(len(fitting)))])
        if gaps:  # dense lane: the largest gap is the best chance
            return float(max(gaps)[1])
        return float(rng.uniform(lo, hi))
