"""The two ways to apply a safety verdict to the agent's choice: replace and mask.

* **replace** (the default, docs/safety.md): the agent proposes any action; an unsafe one is
  replaced by keep lane. The learner stores the action that was applied.
* **mask**: the agent chooses the best *allowed* action (:func:`masked_argmax`, also inside the
  learner's target, :meth:`der_ros.agent.dqn.DQNAgent.act` and ``target_mask``).

Keep lane is always allowed: the shield decides lane changes only; following the leader on the own
lane is SUMO's car-following model's job. For the same reason the speed actions of scenarios that have
them (``faster`` / ``slower``: they only move the ego's target speed, and SUMO's car-following still
keeps the distance to the leader) are always allowed (:func:`with_speed_actions`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["KEEP", "replace_unsafe", "masked_argmax", "with_speed_actions"]

#: the action every verdict allows (``ACTION_NAMES[0]``)
KEEP = 0


def with_speed_actions(mask: np.ndarray, n_actions: int) -> np.ndarray:
    """The lane verdict ``mask`` (keep, left, right; last axis) widened to ``n_actions``: the speed actions
    (indices 3 and up) allowed, as keep lane is. ``n_actions`` <= the mask's width returns it unchanged."""
    m = np.asarray(mask, dtype=bool)
    extra = int(n_actions) - m.shape[-1]
    if extra <= 0:
        return m
    return np.concatenate([m, np.ones((*m.shape[:-1], extra), dtype=bool)], axis=-1)


def replace_unsafe(action: int, mask: np.ndarray | None) -> tuple[int, bool]:
    """``(applied action, intervened)``: ``action`` if ``mask`` allows it, else keep lane.

    ``mask`` None (no shield) allows everything; an action outside the mask is unsafe too.
    """
    a = int(action)
    if mask is None:
        return a, False
    if 0 <= a < len(mask) and bool(mask[a]):
        return a, False
    return KEEP, a != KEEP


def masked_argmax(q_values: np.ndarray, mask: np.ndarray | None) -> int:
    """argmax of ``q_values`` over the allowed actions (ties: the lowest index, as numpy's argmax)."""
    q = np.asarray(q_values, dtype=np.float64)
    if mask is None:
        return int(q.argmax())
    return int(np.where(np.asarray(mask, dtype=bool), q, -np.inf).argmax())
