"""The RSS mask of a batch of stored observations: the learner's target in mask mode.

In mask mode the target's max runs over the actions allowed in the *next* state
(``y = r + gamma max_{a' allowed in s'} Q_target(s', a')``). The replay stores observations, not
points, so the mask is recomputed from the observation vector of :mod:`sumo_bridge.observation`,
which carries everything the RSS check reads: the ego's speed (``speed / speed_scale``), whether
a lane exists on each side, and per slot the present flag, ``gap / neighbour_range`` and
``rel_speed / speed_scale``. It equals :class:`der_ros.safety.checker.RssChecker`'s mask on the
points up to float32 rounding, as long as the ego's speed stays below ``speed_scale`` and relative
speeds within +-``speed_scale`` (20 m/s on the shipped configs; the observation clips beyond).
The ``beyond_lane`` check (cars two lanes away) is not applied: the observation does not carry
that lane, so in those states the target's max may run over a change the acting mask refused (a
rare, optimistic target; docs/safety.md, "The exit scenario"). Vectorised numpy: one call per batch.
"""

from __future__ import annotations

import numpy as np

from der_ros.safety.apply import with_speed_actions
from der_ros.safety.checker import N_ACTIONS
from der_ros.safety.config import SafetyConfig
from sumo_bridge.observation import EGO_FEATURES, SLOT_FEATURES, SLOT_NAMES, ObservationConfig

__all__ = ["ObservationMask"]

_EGO = {name: i for i, name in enumerate(EGO_FEATURES)}
_FEAT = {name: i for i, name in enumerate(SLOT_FEATURES)}


def _slot_col(slot: str, feature: str) -> int:
    return len(EGO_FEATURES) + len(SLOT_FEATURES) * SLOT_NAMES.index(slot) + _FEAT[feature]


def _rss(v_rear: np.ndarray, v_front: np.ndarray, cfg: SafetyConfig, brake_min: float | None = None) -> np.ndarray:
    """:func:`der_ros.safety.rss.safe_longitudinal_distance` on arrays, plus the margin (``brake_min``: the
    rear car's, default ``cfg.brake_min``)."""
    rho, acc = cfg.response_time, cfg.accel_max
    b_min = cfg.brake_min if brake_min is None else brake_min
    v_r, v_f = np.maximum(v_rear, 0.0), np.maximum(v_front, 0.0)
    v_after = v_r + rho * acc
    d = v_r * rho + 0.5 * acc * rho * rho + v_after * v_after / (2.0 * b_min) - v_f * v_f / (2.0 * cfg.brake_max)
    return np.maximum(d, 0.0) + cfg.margin


class ObservationMask:
    """``mask(obs_batch)`` -> bool array ``(batch, n_actions)``: True where an action is safe (the speed
    actions of a five-action scenario always, :func:`der_ros.safety.apply.with_speed_actions`)."""

    def __init__(self, cfg: SafetyConfig, obs_cfg: ObservationConfig, n_actions: int = N_ACTIONS) -> None:
        self.cfg, self.obs_cfg, self.n_actions = cfg, obs_cfg, int(n_actions)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float64)
        if x.ndim == 1:
            x = x[None, :]
        scale, rng = self.obs_cfg.speed_scale, self.obs_cfg.neighbour_range
        v_ego = x[:, _EGO["speed"]] * scale
        out = np.zeros((x.shape[0], N_ACTIONS), dtype=bool)
        out[:, 0] = True
        for action, side, has_lane in ((1, "left", "has_left_lane"), (2, "right", "has_right_lane")):
            ok = x[:, _EGO[has_lane]] > 0.5
            for role, is_leader in (("leader", True), ("follower", False)):
                slot = f"{side}_{role}"
                present = x[:, _slot_col(slot, "present")] > 0.5
                gap = x[:, _slot_col(slot, "gap")] * rng
                v = v_ego + x[:, _slot_col(slot, "rel_speed")] * scale
                need = _rss(v_ego, v, self.cfg, self.cfg.ego_braking) if is_leader else _rss(v, v_ego, self.cfg)
                ok &= ~present | (gap > need)
                if not is_leader and self.cfg.unobserved_speed > 0.0:  # the unseen follower at the range
                    unseen = _rss(np.full_like(v_ego, self.cfg.unobserved_speed), v_ego, self.cfg, self.cfg.unobserved_brake)
                    ok &= present | (rng > unseen)
            if self.cfg.lane_end and self.obs_cfg.goal_distance_scale > 0:  # the diverge ahead (observed)
                toward = x[:, _EGO["target_direction"]] * (1 if side == "left" else -1) > 0.5
                to_diverge = x[:, -1] * self.obs_cfg.goal_distance_scale
                forced = np.where(to_diverge > 0, v_ego * v_ego / (2.0 * np.maximum(to_diverge, 1e-9)), 0.0)
                ok &= toward | (forced <= self.cfg.brake_max)
            out[:, action] = ok
        return with_speed_actions(out, self.n_actions)
