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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from der_ros.configuration import ConfigError, param

__all__ = ["SAFETY_KINDS", "SAFETY_MODES", "SafetyConfig"]

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

    def check(self) -> None:
        for name in ("response_time", "accel_max", "brake_min", "brake_max", "margin"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"safety.{name} = {value!r}, expected a finite number")

    @property
    def enabled(self) -> bool:
        return self.kind != "none"
