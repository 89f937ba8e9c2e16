"""Exploration schedule of the epsilon-greedy policy (paper section 2.1).

The paper's DQN explores with an epsilon-greedy policy but does not say how epsilon changes. We use
the usual linear decay (Mnih et al. 2015): epsilon falls from ``start`` to ``end`` over
``decay_steps`` environment steps and stays at ``end`` afterwards. It is a pure function of the
step count, so a resumed run gets the same epsilon as the uninterrupted one without extra state.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["LinearSchedule"]


@dataclass(frozen=True)
class LinearSchedule:
    """``value(step)`` goes linearly from ``start`` (step 0) to ``end`` (step ``decay_steps``), then stays."""

    start: float
    end: float
    decay_steps: int

    def __post_init__(self) -> None:
        if self.decay_steps < 0:
            raise ValueError(f"decay_steps = {self.decay_steps!r}, expected >= 0")

    def value(self, step: int) -> float:
        if self.decay_steps == 0 or step >= self.decay_steps:
            return float(self.end)
        if step <= 0:
            return float(self.start)
        frac = step / self.decay_steps
        return float(self.start + frac * (self.end - self.start))

    __call__ = value
