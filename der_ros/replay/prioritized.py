"""PrioritizedReplay: proportional prioritized experience replay (Schaul et al. 2015, PER).

* priority p_i = (|delta_i| + eps)^alpha, kept in a :class:`SumTree`; P(i) = p_i / sum_k p_k;
* a new transition enters at the largest priority seen so far ("new transitions arrive
  without a known TD-error, so we put them at maximal priority"), 1.0 before any update;
* sampling is stratified: [0, total) is cut into B equal segments, one draw in each;
* importance weights w_i = (N * P(i))^-beta / max_j w_j, the max over the batch (so the
  largest weight is exactly 1 and updates are only scaled down);
* beta grows linearly from beta0 to 1 over ``beta_steps`` calls of :meth:`sample`:
  the k-th call (k = 0, 1, ...) uses beta0 + (1 - beta0) * min(1, k / beta_steps).

TD errors must be finite: a NaN or inf TD error means the learner diverged, and storing it
would poison the tree, so :meth:`update_priorities` raises ``ValueError`` instead.
Priorities are capped at :data:`MAX_PRIORITY` so that the tree total stays finite.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError
from der_ros.replay.base import Batch, ReplayBuffer, check_batch_size, check_td_errors
from der_ros.replay.storage import RingStorage, check_storage_memory
from der_ros.replay.sum_tree import SumTree

__all__ = ["PrioritizedReplay", "MAX_PRIORITY"]

#: priorities are clipped here so a sum of up to 1e100 of them cannot overflow float64
MAX_PRIORITY = 1e200


class PrioritizedReplay(ReplayBuffer):
    """Proportional PER over the last ``capacity`` transitions."""

    kind = "per"
    importance_weighted = True

    def __init__(
        self,
        capacity: int,
        obs_shape: Sequence[int],
        obs_dtype: np.dtype | str | type = np.float32,
        alpha: float = 0.6,
        beta0: float = 0.4,
        beta_steps: int = 100_000,
        eps: float = 1e-6,
        seed: int | None = 0,
        check_memory: bool = True,
        available_bytes: int | None = None,
    ) -> None:
        if int(capacity) <= 0:
            raise ConfigError(f"capacity = {capacity}, expected >= 1")
        for name, value, lo, hi in (("alpha", alpha, 0.0, 1.0), ("beta0", beta0, 0.0, 1.0)):
            if not lo <= value <= hi:
                raise ConfigError(f"{name} = {value}, expected >= {lo} and <= {hi}")
        if beta_steps < 0:
            raise ConfigError(f"beta_steps = {beta_steps}, expected >= 0")
        if not eps > 0:
            raise ConfigError(f"per_eps = {eps}, expected > 0")
        if check_memory:
            check_storage_memory(capacity, obs_shape, obs_dtype, available_bytes)
        self.capacity = int(capacity)
        self.alpha = float(alpha)
        self.beta0 = float(beta0)
        self.beta_steps = int(beta_steps)
        self.eps = float(eps)
        self.storage = RingStorage(capacity, obs_shape, obs_dtype)
        self.tree = SumTree(capacity)
        self.size = 0
        self.max_priority = 1.0
        self.sample_calls = 0
        self._rng = np.random.default_rng(seed)

    @property
    def beta(self) -> float:
        """beta for the next sample() call (linear from beta0 to 1 over beta_steps calls)."""
        if self.beta_steps <= 0:
            return 1.0
        frac = min(1.0, self.sample_calls / self.beta_steps)
        return self.beta0 + (1.0 - self.beta0) * frac

    def add_batch(self, obs, actions, rewards, next_obs, terminated, truncated) -> None:  # noqa: D102
        slots = self.storage.append_batch(obs, actions, rewards, next_obs, terminated, truncated)
        k = slots.size
        self.tree.set(slots, np.full(k, self.max_priority), check=False)
        self.size = min(self.size + k, self.capacity)

    def add(self, obs, action, reward, next_obs, terminated, truncated) -> None:  # noqa: D102
        slot = self.storage.cursor
        self.storage.put_one(slot, obs, action, reward, next_obs, terminated, truncated)
        self.storage.next_slot()
        self.tree.set(np.array([slot], dtype=np.int64), np.array([self.max_priority]), check=False)
        if self.size < self.capacity:
            self.size += 1

    def _newest_slot(self) -> tuple[RingStorage, int]:
        return self.storage, (self.storage.cursor - 1) % self.capacity

    def sample(self, batch_size: int) -> Batch:
        check_batch_size(batch_size, self.capacity, self.size)
        beta = self.beta
        self.sample_calls += 1
        slots = self.tree.sample(self._rng, batch_size, limit=self.size, positive=True)
        p = self.tree.leaves.take(slots)
        # (N P_i)^-beta / max_j (N P_j)^-beta = (p_min / p_i)^beta; N and the total cancel
        weights = np.power(p.min() / p, beta).astype(np.float32)
        obs, act, rew, nobs, term, trunc = self.storage.gather(slots)
        return Batch(obs, act, rew, nobs, term, trunc, slots, weights, np.zeros(batch_size, dtype=np.uint8))

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """p_i = (|delta_i| + eps)^alpha for the sampled slots; duplicates: the last row wins
        (a DQN step gives every copy of a transition the same delta)."""
        idx, td = check_td_errors(indices, td_errors)
        if idx.size == 0:
            return
        if idx.min() < 0 or idx.max() >= self.size:
            raise IndexError(f"update_priorities: index out of range [0, {self.size}): {idx.min()}..{idx.max()}")
        prio = np.power(np.abs(td) + self.eps, self.alpha)
        np.minimum(prio, MAX_PRIORITY, out=prio)
        self.tree.set(idx, prio, check=False)
        m = float(prio.max())
        if m > self.max_priority:
            self.max_priority = m

    def __len__(self) -> int:
        return self.size

    def stats(self) -> dict[str, float]:
        return {"replay/size": float(self.size), "replay/per_beta": float(self.beta)}

    def _ctor_kwargs(self) -> dict[str, Any]:
        return {
            "capacity": self.capacity,
            "obs_shape": list(self.storage.obs_shape),
            "obs_dtype": self.storage.obs_dtype.str,
            "alpha": self.alpha,
            "beta0": self.beta0,
            "beta_steps": self.beta_steps,
            "eps": self.eps,
        }

    def _arrays(self) -> dict[str, np.ndarray]:
        out = self.storage.arrays("data")
        out["tree/leaves"] = self.tree.leaves
        out["counters"] = np.array([self.size, self.sample_calls], dtype=np.int64)
        out["max_priority"] = np.array(self.max_priority, dtype=np.float64)
        return out

    def _set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self.storage.set_arrays(arrays, "data")
        self.tree.leaves[...] = arrays["tree/leaves"]
        self.tree.rebuild()
        self.size, self.sample_calls = (int(x) for x in arrays["counters"])
        self.max_priority = float(arrays["max_priority"])
