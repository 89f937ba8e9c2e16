"""Settings of the safety layer (one dataclass: YAML ``safety:`` sections, CLI flags, node parameters).

Physical meaning of the RSS parameters (Shalev-Shwartz et al. 2017, definition 1): every car,
the ego and SUMO's drivers alike, is assumed to react within ``response_time`` seconds, to
accelerate at most at ``accel_max`` while it has not reacted, then to brake at least at
``brake_min``; a car ahead may brake at up to ``brake_max``. The defaults were chosen on the
tuning seeds (docs/safety.md, "Choosing the parameters"; research/tuning/shield_params.py): the
response time is one SUMO simulation step (0.1 s, the step its drivers react in), the acceleration
SUMO's passenger car's (2.6 m/s^2), and both brakings its emergency deceleration (9 m/s^2): every
driver is assumed able to brake as hard as the car ahead of it. Textbook RSS assumes less of the
rear car (brake_min 4-4.5); on the ring that halves the success of a driver that changes whenever
allowed (105 of 200 tuning episodes against 200), with no caused collision either way.

``unobserved_speed`` covers what the observation does not show: with it > 0 an empty follower slot
on the target side stands for a vehicle just beyond the neighbour range driving at that speed (RSS's
worst case for an occluded car). On the ``exit`` scenario a slow ego (1-7 m/s at the split) changed in
front of cars at 25-29 m/s 32-37 m behind, just out of sight, and was hit; ``lane_end`` refuses a change
away from the target lane that would make the ego stop harder than ``brake_max`` at the split
(docs/safety.md, "The exit scenario"); ``beyond_lane`` treats a car two lanes away as a possible
intruder into the target lane (the same section, cause C). A scenario file's ``safety:`` section states its fleet's
worst case (:func:`fleet_cautious`); the shield then takes the more cautious of the two values.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

from der_ros.configuration import ConfigError, param

__all__ = ["SAFETY_KINDS", "SAFETY_MODES", "SafetyConfig", "fleet_cautious"]

#: ``none``: no shield; ``rss``: our RSS check on the observed neighbours; ``sumo``: SUMO's own verdict
SAFETY_KINDS: tuple[str, ...] = ("none", "rss", "sumo")
#: ``replace``: an unsafe command becomes keep lane; ``mask``: the agent picks the best allowed action
SAFETY_MODES: tuple[str, ...] = ("replace", "mask")


@dataclass
class SafetyConfig:
    """Which shield sits between the agent and the vehicle, and its RSS parameters."""

    kind: str = param(
        "none",
        "the shield: 'none' (the agent's command goes through), 'rss' (a lane change is allowed only when the "
        "new leader and the new follower in the target lane keep the RSS safe distance), 'sumo' (SUMO's own "
        "lane-change model must find the change unblocked; needs the simulation in the same process)",
        choices=SAFETY_KINDS,
    )
    mode: str = param(
        "replace",
        "how the verdict reaches the agent: 'replace' (an unsafe command becomes keep lane; the learner stores "
        "the applied action) or 'mask' (the agent chooses the best allowed action, in acting and in its "
        "target's max; needs kind 'rss' in training)",
        choices=SAFETY_MODES,
    )
    response_time: float = param(
        0.1,
        "RSS rho, seconds: how long a car may keep accelerating before it reacts (0.1 = one SUMO simulation "
        "step of the shipped configs, the step SUMO's drivers react in)",
        low=0.0,
        high=5.0,
    )
    accel_max: float = param(
        2.6,
        "m/s^2: the largest acceleration of the rear car during the response time (SUMO passenger car: 2.6)",
        low=0.0,
        high=20.0,
    )
    brake_min: float = param(
        9.0,
        "m/s^2 (> 0): the braking the rear car applies at least once it reacts (9 = SUMO passenger car's emergency "
        "decel; its comfortable decel is 4.5)",
        low=0.1,
        high=20.0,
    )
    brake_max: float = param(
        9.0,
        "m/s^2 (> 0): the hardest braking of the front car (SUMO passenger car's emergency decel: 9)",
        low=0.1,
        high=20.0,
    )
    margin: float = param(
        0.0,
        "metres added to every RSS safe distance (bumper to bumper), e.g. for sensor noise",
        low=0.0,
        high=100.0,
    )
    unobserved_speed: float = param(
        0.0,
        "m/s: > 0: an empty follower slot on the target side is taken to hold a car just beyond the neighbour "
        "range (30 m) driving at this speed, and the change must keep the RSS distance to it; 0 (the ring's "
        "setting): an empty slot imposes nothing. A scenario file's safety section may raise it",
        low=0.0,
        high=100.0,
    )
    lane_end: bool = param(
        False,
        "true: a change that does not move toward the target lane is unsafe when the ego would then have to brake "
        "harder than brake_max to stop at the diverge ahead (the ego row's gap; scenario files with a goal edge, "
        "where every other lane ends for the ego). No effect where that gap is 0 (ring, urban)",
    )
    beyond_lane: bool = param(
        False,
        "true: a car on the lane beyond the target lane (two lanes away, in process: the env's info['beyond_points']) "
        "counts as a possible new leader or follower in the target lane, since it may change into it in the same step "
        "as the ego: the change must keep the RSS distance to it too. The state message and the observation do not "
        "carry that lane, so safety_node and the mask-mode target mask cannot apply it",
    )
    ego_brake: float = param(
        0.0,
        "m/s^2: the braking the ego applies at least once it reacts, as the rear car behind a new leader; 0 (the "
        "default): brake_min. Lower it for an ego that cannot brake as hard as the other cars, e.g. a SUMO ego held "
        "at a TraCI setSpeed target with speed mode 31, which brakes at its decel (4.5), never at its emergencyDecel "
        "(docs/safety.md, 'The own-lane leader')",
        low=0.0,
        high=20.0,
    )
    unobserved_brake: float = param(
        9.0,
        "m/s^2 (> 0): the braking that unobserved car applies at least once it reacts (a car at the speed limit: "
        "SUMO's passenger car's emergency decel, 9; brake_min may be lower for the observed followers, e.g. trucks)",
        low=0.1,
        high=20.0,
    )

    def check(self) -> None:
        for name in ("response_time", "accel_max", "brake_min", "brake_max", "margin", "unobserved_speed",
                     "unobserved_brake", "ego_brake"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"safety.{name} = {value!r}, expected a finite number")

    @property
    def ego_braking(self) -> float:
        """The ego's braking as a rear car (m/s^2): ``ego_brake``, or ``brake_min`` when that is 0."""
        return float(self.ego_brake) if self.ego_brake > 0.0 else self.brake_min

    @property
    def enabled(self) -> bool:
        return self.kind != "none"


#: scenario ``safety:`` fields -> True where a larger value is the more cautious one
FLEET_FIELDS: dict[str, bool] = {"response_time": True, "accel_max": True, "brake_min": False, "brake_max": True,
                                 "unobserved_speed": True, "unobserved_brake": False, "lane_end": True,
                                 "beyond_lane": True, "ego_brake": False}  # fmt: skip


def fleet_cautious(cfg: SafetyConfig, fleet: Mapping[str, float | bool | None]) -> SafetyConfig:
    """``cfg`` made at least as cautious as a scenario's fleet (its file's ``safety:`` section).

    Per field the more cautious of the two: the longer response time, the larger acceleration and
    front-car braking, the *smaller* rear-car braking (a truck that stops at 7 m/s^2 cannot be assumed
    to brake at 9), the faster unobserved car, the lane-end and beyond-lane checks on if either asks for them. Fields the section leaves out (None) keep ``cfg``'s
    value, so a scenario without the section (ring, urban) leaves the shield exactly as configured.
    """
    changes: dict[str, float | bool] = {}
    for name, larger in FLEET_FIELDS.items():
        value = fleet.get(name)
        if value is None:
            continue
        mine = getattr(cfg, name)
        if name == "ego_brake":  # 0: brake_min's value is in force
            mine = cfg.ego_braking
        pick = max(mine, value) if larger else min(mine, value)
        if pick != mine:
            changes[name] = type(mine)(pick)
    return dataclasses.replace(cfg, **changes) if changes else cfg
