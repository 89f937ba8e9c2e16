"""The shield as a gymnasium wrapper: ``der train``, ``der table3`` and ``der baselines`` in process.

The wrapper checks every step's command against the verdict on the state it is applied in (the
points of the last ``reset``/``step``) and, in both modes, replaces an unsafe one by keep lane
(replace mode relies on this; in mask mode the agent already chose an allowed action, so the
wrapper only guards). It adds to ``info``:

* ``action_mask`` -- the safe actions in the *returned* state (bool, keep/left/right, and the speed actions, always allowed): what the
  next command is checked against, and what a mask-mode agent chooses from;
* ``proposed_action``, ``applied_action``, ``intervened`` -- this step's command, what was applied
  and whether the shield changed it (``step`` only);
* ``interventions`` -- the episode's interventions so far.

The environment must be a lane-change env (``info["points"]``); ``kind: sumo`` also needs its
simulation (``env.unwrapped.api`` and ``ego_id``) in this process. The RSS parameters are the
configured ones made at least as cautious as the scenario file's ``safety:`` section
(:func:`scenario_shield`; the ring and urban have none, so their shield is exactly as configured).
"""

from __future__ import annotations

import logging
from typing import Any

import gymnasium as gym
import numpy as np

from der_ros.configuration import ConfigError
from der_ros.safety.apply import replace_unsafe, with_speed_actions
from der_ros.safety.checker import RssChecker
from der_ros.safety.config import SafetyConfig, fleet_cautious
from der_ros.safety.observation_mask import ObservationMask
from der_ros.safety.sumo_check import sumo_mask
from sumo_bridge import ENV_NETWORKS
from sumo_bridge.scenario import ScenarioConfig
from sumo_bridge.scenario_file import load_scenario, scenario_from_kwargs

log = logging.getLogger(__name__)

__all__ = ["ShieldWrapper", "scenario_shield", "shield_in_force", "target_mask_for"]


def scenario_shield(cfg: SafetyConfig, scenario: ScenarioConfig | None) -> SafetyConfig:
    """The shield's parameters on ``scenario``: ``cfg`` made at least as cautious as the fleet its file's
    ``safety:`` section states (:func:`der_ros.safety.config.fleet_cautious`); ``cfg`` itself for a
    scenario without a file or section."""
    if scenario is None or not scenario.file:
        return cfg
    return fleet_cautious(cfg, load_scenario(scenario.file).safety)


class ShieldWrapper(gym.Wrapper):
    """Replace unsafe lane-change commands by keep lane; publish the verdict in ``info``."""

    def __init__(self, env: gym.Env, cfg: SafetyConfig) -> None:
        super().__init__(env)
        if not cfg.enabled:
            raise ConfigError("safety.kind = 'none': nothing to wrap")
        scenario = getattr(env.unwrapped, "config", None)
        scenario = scenario if isinstance(scenario, ScenarioConfig) else None
        #: the parameters in force: ``cfg`` and the scenario's fleet (:func:`scenario_shield`)
        self.cfg = scenario_shield(cfg, scenario)
        if self.cfg != cfg:
            log.info("shield: %s's safety section makes it %s", scenario.network if scenario else "?", self.cfg)
        rng = scenario.observation.neighbour_range if scenario is not None else None
        self._rss = (RssChecker(self.cfg) if rng is None else RssChecker(self.cfg, rng)) if cfg.kind == "rss" else None
        if self._rss is not None and self.cfg.beyond_lane:  # the env then reads the lanes two out too
            watch = getattr(env.unwrapped, "watch_beyond_lanes", None)
            if watch is None:
                raise ConfigError("safety.beyond_lane = true needs a lane-change env that reads the lanes two to "
                                  f"either side; {env.unwrapped!r} does not")  # fmt: skip
            watch()
        self._mask: np.ndarray | None = None
        #: the env's actions: the speed actions beyond keep/left/right are allowed (with_speed_actions)
        self._n_actions = int(getattr(env.action_space, "n", 3))
        self.interventions = 0

    def verdict(self, info: dict[str, Any]) -> np.ndarray:
        """The safe actions in the state ``info`` describes."""
        points = info.get("points")
        if points is None:
            raise ConfigError(f"safety.kind = {self.cfg.kind!r} needs a lane-change env (info['points']); "
                              f"{self.env.spec.id if self.env.spec else self.env!r} has none")  # fmt: skip
        if self._rss is not None:
            return with_speed_actions(self._rss.mask(points, info.get("beyond_points")), self._n_actions)
        inner = self.env.unwrapped
        return with_speed_actions(sumo_mask(inner.api, inner.ego_id, points), self._n_actions)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self.interventions = 0
        self._mask = self.verdict(info)
        info["action_mask"] = self._mask
        info["interventions"] = 0
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        applied, intervened = replace_unsafe(int(action), self._mask)
        self.interventions += intervened
        obs, reward, terminated, truncated, info = self.env.step(applied)
        self._mask = self.verdict(info)
        info.update(action_mask=self._mask, proposed_action=int(action), applied_action=applied,
                    intervened=intervened, interventions=self.interventions)  # fmt: skip
        return obs, reward, terminated, truncated, info


def shield_in_force(env_cfg: Any) -> SafetyConfig:
    """The shield parameters an :class:`der_ros.train.config.EnvConfig` runs with: its ``safety`` and, on a
    lane-change env, its scenario's fleet (:func:`scenario_shield`). What caches and records should name."""
    network = ENV_NETWORKS.get(env_cfg.id)
    if network is None or not env_cfg.safety.enabled:
        return env_cfg.safety
    return scenario_shield(env_cfg.safety, scenario_from_kwargs(network, dict(env_cfg.kwargs).get("scenario")))


def target_mask_for(env_cfg: Any) -> ObservationMask | None:
    """The learner's next-state mask (mask mode) for an :class:`der_ros.train.config.EnvConfig`.

    None without a shield or in replace mode. Mask mode needs ``kind: rss``: SUMO's verdict on a
    stored state cannot be recomputed from its observation.
    """
    cfg: SafetyConfig = env_cfg.safety
    if not cfg.enabled or cfg.mode != "mask":
        return None
    if cfg.kind != "rss":
        raise ConfigError(f"env.safety.mode = 'mask' with kind = {cfg.kind!r}: mask mode needs kind 'rss' (the "
                          "learner recomputes the next state's mask from the stored observation)")  # fmt: skip
    network = ENV_NETWORKS.get(env_cfg.id)
    if network is None:
        raise ConfigError(f"env.safety.kind = 'rss' needs a lane-change env id {tuple(ENV_NETWORKS)}, got {env_cfg.id!r}")
    scenario = scenario_from_kwargs(network, dict(env_cfg.kwargs).get("scenario"))
    return ObservationMask(scenario_shield(cfg, scenario), scenario.observation, len(scenario.actions))
