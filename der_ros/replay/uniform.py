"""UniformReplay: the plain DQN buffer (Mnih et al. 2015) -- every stored transition is
equally likely, sampled with replacement; the oldest is overwritten when full."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError
from der_ros.replay.base import Batch, ReplayBuffer, check_batch_size
from der_ros.replay.storage import RingStorage, check_storage_memory

__all__ = ["UniformReplay"]


class UniformReplay(ReplayBuffer):
    """Uniform sampling with replacement over the last ``capacity`` transitions."""

    kind = "uniform"

    def __init__(
        self,
        capacity: int,
        obs_shape: Sequence[int],
        obs_dtype: np.dtype | str | type = np.float32,
        seed: int | None = 0,
        check_memory: bool = True,
        available_bytes: int | None = None,
    ) -> None:
        if int(capacity) <= 0:
            raise ConfigError(f"capacity = {capacity}, expected >= 1")
        if check_memory:
            check_storage_memory(capacity, obs_shape, obs_dtype, available_bytes)
        self.storage = RingStorage(capacity, obs_shape, obs_dtype)
        self.capacity = int(capacity)
        self.size = 0
        self._rng = np.random.default_rng(seed)

    def add_batch(self, obs, actions, rewards, next_obs, terminated, truncated) -> None:  # noqa: D102
        slots = self.storage.append_batch(obs, actions, rewards, next_obs, terminated, truncated)
        self.size = min(self.size + slots.size, self.capacity)

    def add(self, obs, action, reward, next_obs, terminated, truncated) -> None:  # noqa: D102
        self.storage.put_one(self.storage.next_slot(), obs, action, reward, next_obs, terminated, truncated)
        if self.size < self.capacity:
            self.size += 1

    def _newest_slot(self) -> tuple[RingStorage, int]:
        return self.storage, (self.storage.cursor - 1) % self.capacity

    def sample(self, batch_size: int) -> Batch:
        check_batch_size(batch_size, self.capacity, self.size)
        slots = self._rng.integers(0, self.size, batch_size, dtype=np.int64)
        obs, act, rew, nobs, term, trunc = self.storage.gather(slots)
        return Batch(
            obs, act, rew, nobs, term, trunc,
            slots,
            np.ones(batch_size, dtype=np.float32),
            np.zeros(batch_size, dtype=np.uint8),
        )  # fmt: skip

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """No-op: uniform replay has no priorities (kept so the learner never special-cases)."""

    def __len__(self) -> int:
        return self.size

    def stats(self) -> dict[str, float]:
        return {"replay/size": float(self.size)}

    def _ctor_kwargs(self) -> dict[str, Any]:
        return {
            "capacity": self.capacity,
            "obs_shape": list(self.storage.obs_shape),
            "obs_dtype": self.storage.obs_dtype.str,
        }

    def _arrays(self) -> dict[str, np.ndarray]:
        out = self.storage.arrays("data")
        out["size"] = np.array(self.size, dtype=np.int64)
        return out

    def _set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self.storage.set_arrays(arrays, "data")
        self.size = int(arrays["size"])

