"""ScenarioConfig: everything that defines one lane-change scenario (paper section 5.1).

One dataclass for both networks; :func:`ScenarioConfig.ring` and :func:`ScenarioConfig.urban`
give the defaults of the two registered environments. Every field is declared with
:func:`der_ros.configuration.param`, so YAML files (``config/ring.yaml``, ``config/urban.yaml``),
CLI flags and ROS parameters share the same checks; a bad value raises
:class:`~der_ros.configuration.ConfigError` naming the field and the value.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from der_ros.configuration import ConfigError, from_dict, param, to_dict, validate
from sumo_bridge.network_build import NETWORK_NAMES
from sumo_bridge.observation import ObservationConfig

__all__ = ["ScenarioConfig", "scenario_from_kwargs", "ACTION_SETS", "LANE_CHANGE_PARAMS", "lane_change_params"]

#: The action sets a scenario may use; index = action value (der_ros.contract carries the same values).
ACTION_SETS: tuple[tuple[str, ...], ...] = (("keep", "left", "right"), ("keep", "left", "right", "faster", "slower"))

#: SUMO LC2013 parameters an ego may get through ``ego_lane_change_params`` (SUMO's vType attributes of the
#: same names; docs: "Lane-Changing Models")
LANE_CHANGE_PARAMS: tuple[str, ...] = (
    "lcStrategic", "lcCooperative", "lcSpeedGain", "lcKeepRight", "lcOvertakeRight", "lcLookaheadLeft",
    "lcSpeedGainRight", "lcAssertive", "lcImpatience", "lcTimeToImpatience", "lcAccelLat", "lcSigma",
)  # fmt: skip


def lane_change_params(entries: tuple[str, ...] | list[str]) -> dict[str, float]:
    """``('lcAssertive=3', ...)`` as ``{'lcAssertive': 3.0}``; a :class:`ConfigError` names a malformed entry."""
    out: dict[str, float] = {}
    for entry in entries:
        name, sep, value = str(entry).partition("=")
        name = name.strip()
        if not sep or name not in LANE_CHANGE_PARAMS:
            raise ConfigError(f"ego_lane_change_params: {entry!r}, expected 'name=value' with name one of "
                              f"{', '.join(LANE_CHANGE_PARAMS)}")  # fmt: skip
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number):
            raise ConfigError(f"ego_lane_change_params: {entry!r}, expected a finite number after '='")
        out[name] = number
    return out


@dataclass
class ScenarioConfig:
    """A SUMO lane-change scenario: network, traffic, timing, reward and observation."""

    network: str = param(
        "ring",
        "the scenario's name: 'ring' (two concentric lanes) and 'urban' (bridge) are built in; any other name "
        "needs ``file`` (a scenario file, see docs/scenarios.md)",
    )
    file: str = param(
        "",
        "path of a scenario file (sumo_bridge.scenario_file) whose network, demand, ego and goal the env "
        "runs; '' = the built-in ring or urban set-up named by ``network``",
    )
    actions: tuple[str, ...] = param(
        ACTION_SETS[0],
        "the action set: ['keep', 'left', 'right'] (the paper's, the default) or ['keep', 'left', 'right', "
        "'faster', 'slower'] (speed actions: the ego's target speed steps by speed_step; SUMO's car-following "
        "keeps it safe)",
    )
    speed_step: float = param(2.0, "m/s the ego's target speed changes by with 'faster' / 'slower'", low=0.0, low_inclusive=False)
    reward_missed: float = param(
        0.0,
        "file scenarios with a goal edge: reward when the ego misses it (event 'missed', terminated). 0 (default): "
        "a missed exit forfeits reward_success and ends the episode, as a failed change pays nothing in the paper's "
        "task; -100 is kept for harming others (see docs/scenarios.md)",
    )
    backend: str = param(
        "libsumo", "'libsumo' (in process, fast, one per process) or 'traci' (sumo subprocess)", choices=("libsumo", "traci")
    )
    gui: bool = param(False, "run sumo-gui (implies the traci backend)")
    seed: int = param(0, "seed used when reset() is first called without a seed", low=0, high=2**31 - 1)
    step_length: float = param(0.1, "SUMO simulation step in seconds", low=0.001, high=5.0)
    decision_interval: int = param(5, "simulation steps per environment step (one lane-change decision)", low=1, high=1000)
    max_episode_steps: int = param(
        50,
        "environment steps of an episode (the fixed horizon): after this many the episode is truncated "
        "(time limit; the learner bootstraps through it); event 'success' if the target lane was reached, "
        "else 'time_limit'",
        low=1,
        high=1_000_000,
    )
    success_ends_episode: bool = param(
        False,
        "False (default): reaching the target lane pays reward_success once and the ego keeps driving to the "
        "horizon, so the speed reward keeps flowing whatever it did and a safe change now is optimal for any "
        "gamma. True: success terminates the episode (our earlier structure; it forfeits the speed reward of "
        "the remaining steps, which makes never changing lane optimal for gamma > ~0.977, see docs/design.md)",
    )
    commit_on_success: bool = param(
        False,
        "True: the authors' 'commit' structure on the same fixed horizon. The step in which the target lane "
        "is reached simulates the rest of the horizon (the task is done, so commands would be no-ops) and pays "
        "reward_success plus the undiscounted sum of the remaining steps' speed rewards (and reward_collision "
        "if a caused collision follows); the episode then terminates. Episode returns equal the fixed "
        "horizon's for the same decisions, but an episode costs only the decisions up to its lane change, so "
        "a budget of environment steps (agent decisions) holds several times more lane-change outcomes. "
        "Requires success_ends_episode and lane_changes_after_success False",
    )
    lane_changes_after_success: bool = param(
        False,
        "False (default): once the target lane is reached the task is done, the ego stays on it and lane-change "
        "commands are no-ops for the rest of the episode (the speed reward keeps flowing). True: commands still "
        "act after success; the bonus is not paid again, so the agent can drift back and forth between lanes "
        "for nothing, and the observation cannot tell a return to the start lane from a fresh start",
    )
    warmup_seconds: float = param(
        5.0, "ring: simulated seconds after placing the vehicles at standstill, before the first observation", low=0.0
    )
    urban_ego_gap_seconds: float = param(
        1.0, "urban: simulated seconds of traffic between removing one episode's ego and inserting the next", low=0.0
    )
    ego_lane: int = param(0, "lane index the ego starts on (SUMO: 0 = rightmost; ring: 0 = outer lane)", low=0)
    target_lane: int = param(
        -1, "lane index the ego must reach; -1 = the network's: ring 1 (inner lane), urban 2 (bridge's left lane)", low=-1
    )
    ring_outer_vehicles: tuple[int, ...] = param(
        (6, 10), "ring: [min, max] background vehicles placed on the outer lane (lane 0) at reset", low=0
    )
    ring_inner_vehicles: tuple[int, ...] = param(
        (15, 21), "ring: [min, max] background vehicles placed on the inner lane (lane 1) at reset", low=0
    )
    slow_fraction: float = param(
        0.3, "ring: fraction of background vehicles of the slower, longer 'slow' type (varied traffic)", low=0.0, high=1.0
    )
    min_spacing: float = param(
        10.0, "ring: smallest front-to-front distance between vehicles placed on one lane (m)", low=8.0
    )
    ring_rebuild_every: int = param(
        4,
        "ring: a reset without a seed rebuilds the traffic (load, seeded placement, 5 s warm-up; 8-14 ms, "
        "20-45 ms under load) once every this many episodes; the resets in between put the last build's warm "
        "traffic back in place with the inner lane rotated by a fresh random offset and one SUMO step "
        "(~0.8 ms under load, sumo_bridge.warm_state). 1 = rebuild at every reset. reset(seed=...) always rebuilds",
        low=1,
    )
    urban_depart_pos: tuple[float, ...] = param(
        (40.0, 400.0), "urban: [min, max] position (m) along the bridge where the ego is inserted", low=0.0
    )
    urban_warmup_seconds: float = param(
        150.0, "urban: simulated seconds of background traffic after a full load, before the first ego", low=0.0
    )
    urban_reload_every: int = param(
        100,
        "urban: episodes between full reloads of the simulation (between them the background traffic keeps "
        "running and only the ego is replaced); 0 = reload only on reset(seed=...)",
        low=0,
    )
    reward_success: float = param(100.0, "reward for reaching the target lane (paper: +100)")
    reward_collision: float = param(-100.0, "reward when the agent causes a collision (paper: -100)")
    min_speed: float = param(
        0.1,
        "speed floor (m/s) in the per-step reward log(max(mean speed, min_speed)), so a standstill gives a "
        "finite reward",
        low=1e-6,
        low_inclusive=True,
    )
    collision_window: float = param(
        3.0,
        "seconds after the ego's own lane change during which a collision involving the ego (as collider or "
        "victim) counts as caused by the agent (reward_collision)",
        low=0.0,
    )
    settle_time: float = param(
        0.4,
        "seconds the ego must stay on the target lane without a collision before 'success' (the change itself "
        "takes one simulation step, so 0.4 s with the default 5 x 0.1 s decision gives the +100 in the same "
        "env step as the lane change)",
        low=0.0,
    )
    ego_lane_change_mode: int = param(
        0,
        "SUMO laneChangeMode of the ego. 0 (the task): no lane change of its own, and a commanded change is "
        "executed in the next simulation step whether safe or not, so the agent alone decides when. 1621 "
        "(SUMO's default): SUMO's own model, which carries out a commanded change only when it finds it "
        "safe, and may change lanes by itself (the 'sumo' baseline of the tables)",
        low=0,
        high=4095,
    )
    background_sigma: float | None = param(
        None,
        "driver imperfection (SUMO's sigma, 0 = perfect, 1 = most dawdling) of every background vehicle type; "
        "None: the scenario's own (0.5 on ring and urban). A traffic shift for evaluation (docs/safety.md)",
        low=0.0,
        high=1.0,
    )
    background_tau: float | None = param(
        None,
        "desired time headway in seconds of every background vehicle type (SUMO's tau; smaller = closer "
        "following, less careful); None: the scenario's own (SUMO's 1 s on ring and urban)",
        low=0.01,
        high=10.0,
    )
    ego_type: str = param(
        "",
        "file scenarios: the vType the ego gets when it is taken over; '' = the scenario file's ego.type. The "
        "IDM+MOBIL baseline drives the exit with 'ego_idm' (SUMO's IDM car-following, sumo_bridge/mobil.py)",
    )
    ego_lane_change_params: tuple[str, ...] = param(
        (),
        "file scenarios: SUMO lane-change model parameters of the ego as 'name=value' (e.g. 'lcAssertive=3'), set "
        "with vehicle.setParameter('laneChangeModel.<name>') when it is taken over; the 'sumo_tuned' baseline's "
        f"tuned LC2013 parameters. Names: {', '.join(LANE_CHANGE_PARAMS)}",
    )
    sumo_args: tuple[str, ...] = param((), "extra command-line arguments for sumo (e.g. ['--lateral-resolution', '0.8'])")
    observation: ObservationConfig = param(
        default_factory=ObservationConfig, help="normalisation of the observation (sumo_bridge.observation)"
    )

    @property
    def target(self) -> int:
        """The target lane index (``target_lane`` with -1 resolved per network)."""
        if self.target_lane >= 0:
            return self.target_lane
        return 1 if self.network == "ring" else 2

    @property
    def step_seconds(self) -> float:
        """Simulated seconds per environment step."""
        return self.step_length * self.decision_interval

    def check(self) -> None:
        if tuple(self.actions) not in ACTION_SETS:
            raise ConfigError(f"actions = {list(self.actions)!r}, expected one of {[list(a) for a in ACTION_SETS]}")
        lane_change_params(self.ego_lane_change_params)  # raises on a malformed entry
        if not self.file:
            for name in ("ego_type", "ego_lane_change_params"):
                if getattr(self, name):
                    raise ConfigError(f"{name} = {getattr(self, name)!r}, expected it empty: only scenario files take "
                                      "over an ego (the ring and urban set-ups insert theirs)")
            if self.network not in NETWORK_NAMES:
                raise ConfigError(
                    f"network = {self.network!r}, expected one of {', '.join(NETWORK_NAMES)} (built in) or a scenario "
                    "file in 'file'"
                )
            self._check_builtin()
        elif self.ego_lane == self.target:
            raise ConfigError(f"target_lane = {self.target_lane!r}, expected a lane other than ego_lane ({self.ego_lane})")

    def _check_builtin(self) -> None:
        for name in ("ring_outer_vehicles", "ring_inner_vehicles", "urban_depart_pos"):
            value = getattr(self, name)
            if len(value) != 2 or value[0] > value[1]:
                raise ConfigError(f"{name} = {list(value)!r}, expected [min, max] with min <= max")
        max_lanes = 2 if self.network == "ring" else 3
        for name in ("ego_lane", "target_lane"):
            value = getattr(self, name)
            if value >= max_lanes:
                raise ConfigError(f"{name} = {value!r}, expected a lane index below {max_lanes} on the {self.network} network")
        if self.ego_lane == self.target:
            raise ConfigError(f"target_lane = {self.target_lane!r}, expected a lane other than ego_lane ({self.ego_lane})")
        if self.network == "ring":
            lap = 376.9
            for name in ("ring_outer_vehicles", "ring_inner_vehicles"):
                most = getattr(self, name)[1] + (1 if name == ("ring_outer_vehicles", "ring_inner_vehicles")[self.ego_lane] else 0)
                if most * self.min_spacing > lap:
                    raise ConfigError(
                        f"{name} = {list(getattr(self, name))!r}, expected at most {int(lap // self.min_spacing)} "
                        f"vehicles per lane with min_spacing {self.min_spacing} m on a {lap} m lap"
                    )
        if self.commit_on_success and (self.success_ends_episode or self.lane_changes_after_success):
            other = "success_ends_episode" if self.success_ends_episode else "lane_changes_after_success"
            raise ConfigError(f"commit_on_success = True with {other} = True, expected {other} False (commit "
                              "simulates the rest of the horizon with the ego held on the target lane)")
        if self.observation.max_lanes < max_lanes:
            raise ConfigError(
                f"observation.max_lanes = {self.observation.max_lanes!r}, expected >= {max_lanes} for the {self.network} network"
            )

    @classmethod
    def ring(cls, **overrides: Any) -> ScenarioConfig:
        """Defaults of ``der_ros/LaneChangeRing-v0`` (validated; overrides by field name)."""
        return from_dict(cls, {"network": "ring", **overrides}, source="ring scenario")

    @classmethod
    def urban(cls, **overrides: Any) -> ScenarioConfig:
        """Defaults of ``der_ros/LaneChangeUrban-v0``: start on the bridge's right lane, reach the left one.

        Same as ``ScenarioConfig(network="urban")``: network-specific defaults are resolved from
        ``network`` (``target``), so the ROS bridge's plain config and the gym id agree.
        """
        return from_dict(cls, {"network": "urban", **overrides}, source="urban scenario")


def scenario_from_kwargs(
    network: str, config: ScenarioConfig | dict[str, Any] | None = None,
    preset: Callable[..., ScenarioConfig] | None = None, **overrides: Any,
) -> ScenarioConfig:
    """Build a validated config from ``gymnasium.make`` keyword arguments.

    Accepts a ready :class:`ScenarioConfig`, a ``scenario``-style mapping, and/or field
    overrides (``gym.make("der_ros/LaneChangeRing-v0", decision_interval=1)``). ``preset``: the defaults
    (``ScenarioConfig.ring`` / ``.urban`` by ``network``; a scenario file's, see
    :func:`sumo_bridge.scenario_file.scenario_from_kwargs`).
    """
    if preset is None:
        preset = ScenarioConfig.ring if network == "ring" else ScenarioConfig.urban
    if isinstance(config, ScenarioConfig):
        data = to_dict(config)
    elif config is None:
        data = to_dict(preset())
    elif isinstance(config, dict):
        data = to_dict(preset(**{k: v for k, v in config.items() if k != "network"}))
        if "network" in config and config["network"] != network:
            raise ConfigError(f"scenario: network = {config['network']!r}, expected {network!r} for this environment id")
    else:
        raise ConfigError(f"scenario = {config!r}, expected a mapping of ScenarioConfig fields")
    if "network" in overrides and overrides["network"] != network:
        raise ConfigError(f"scenario: network = {overrides['network']!r}, expected {network!r} for this environment id")
    obs_override = overrides.pop("observation", None)
    data.update(overrides)
    if obs_override is not None:
        if not isinstance(obs_override, (dict, ObservationConfig)):
            raise ConfigError(f"scenario: observation = {obs_override!r}, expected a mapping")
        obs = to_dict(obs_override) if isinstance(obs_override, ObservationConfig) else obs_override
        data["observation"] = {**data["observation"], **obs}
    cfg = from_dict(ScenarioConfig, data, source="scenario")
    return validate(dataclasses.replace(cfg), source="scenario")

