"""RingStorage: one preallocated numpy array per transition field.

Observations keep the dtype they are declared with (uint8 Atari frames are never upcast:
an 84x84x4 frame stack is 28 KB as uint8 and 113 KB as float32). The memory a buffer
needs is computed before anything is allocated and compared with what the machine has,
so a too-large capacity fails at once with the numbers instead of swapping or being
killed hours into a run.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError

__all__ = [
    "RingStorage",
    "ReplayMemoryError",
    "storage_bytes",
    "available_memory_bytes",
    "check_memory",
    "check_storage_memory",
]

log = logging.getLogger(__name__)

#: per-transition bytes besides the two observations: action int64, reward float32, 2 bools,
#: plus an upper bound on what the samplers keep per slot (dense index, position, generation,
#: de-duplication marker, sum-tree leaf + inner nodes, log-weight: at most 5 x 8 bytes)
_SCALAR_BYTES = 8 + 4 + 1 + 1
_BOOKKEEPING_BYTES = 5 * 8


class ReplayMemoryError(ConfigError):
    """The configured replay capacity does not fit in the available memory."""


def storage_bytes(capacity: int, obs_shape: Sequence[int], obs_dtype: np.dtype | str | type) -> int:
    """Bytes a :class:`RingStorage` of ``capacity`` transitions allocates (obs + next_obs + scalars),
    plus the per-slot bookkeeping of the samplers (sum-tree leaves, indices)."""
    obs_bytes = int(np.prod(obs_shape, dtype=np.int64)) * np.dtype(obs_dtype).itemsize
    return int(capacity) * (2 * obs_bytes + _SCALAR_BYTES + _BOOKKEEPING_BYTES)


def available_memory_bytes() -> int:
    """Memory the OS can give us now (psutil's ``available``, else /proc/meminfo MemAvailable)."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover - psutil is a dependency
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    raise RuntimeError("cannot determine available memory")  # pragma: no cover


def check_memory(
    needed: int,
    what: str,
    available: int | None = None,
    fraction: float = 0.9,
) -> None:
    """Raise :class:`ReplayMemoryError` if ``needed`` bytes exceed ``fraction`` of the available memory.

    ``what`` describes the buffer (capacity, obs shape, dtype) for the message.
    """
    avail = available_memory_bytes() if available is None else int(available)
    if needed > fraction * avail:
        raise ReplayMemoryError(
            f"replay buffer {what} needs {needed:,} bytes ({needed / 2**30:.2f} GiB) but only "
            f"{avail:,} bytes ({avail / 2**30:.2f} GiB) are available (limit {fraction:.0%} of that); "
            "lower the capacity (uint8 observations take a quarter of float32 ones)"
        )
    log.debug("replay buffer %s: %d bytes of %d available", what, needed, avail)


def check_storage_memory(
    capacity: int, obs_shape: Sequence[int], obs_dtype: np.dtype | str | type, available: int | None = None
) -> None:
    """:func:`check_memory` for a buffer made of one :class:`RingStorage` of ``capacity`` transitions."""
    check_memory(storage_bytes(capacity, obs_shape, obs_dtype), describe(capacity, obs_shape, obs_dtype), available)


class RingStorage:
    """Preallocated arrays for ``capacity`` transitions; slots are chosen by the sampler.

    ``next_slots(k)`` hands out ring positions in FIFO order (slot written longest ago
    first), which is what the uniform and prioritized buffers and H1 of DER use.
    """

    def __init__(self, capacity: int, obs_shape: Sequence[int], obs_dtype: np.dtype | str | type) -> None:
        if int(capacity) <= 0:
            raise ConfigError(f"capacity = {capacity}, expected >= 1")
        self.capacity = int(capacity)
        self.obs_shape = tuple(int(d) for d in obs_shape)
        self.obs_dtype = np.dtype(obs_dtype)
        n = self.capacity
        self.obs = np.zeros((n, *self.obs_shape), dtype=self.obs_dtype)
        self.next_obs = np.zeros((n, *self.obs_shape), dtype=self.obs_dtype)
        self.actions = np.zeros(n, dtype=np.int64)
        self.rewards = np.zeros(n, dtype=np.float32)
        self.terminated = np.zeros(n, dtype=np.bool_)
        self.truncated = np.zeros(n, dtype=np.bool_)
        #: the field arrays in FIELDS order (saves getattr calls on the hot path)
        self.arrays_tuple = (self.obs, self.actions, self.rewards, self.next_obs, self.terminated, self.truncated)
        #: next ring position to write
        self.cursor = 0
        #: transitions ever written through next_slots (for FIFO order and stats)
        self.num_written = 0
        #: where this storage's slot 0 lies in the arrays it shares (0; a :meth:`view`'s start)
        self.offset = 0
        #: the storage that owns the arrays (itself; a view's: its parent's owner)
        self._root = self
        #: the deferred transition of this storage and its views: [(root storage, root row, complete)]
        #: or [None] (see :meth:`defer`); one list object shared by a storage and all its views
        self._deferred: list[tuple[RingStorage, int, Callable[[], tuple[Any, ...]]] | None] = [None]

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated", "truncated")

    def view(self, start: int, stop: int) -> RingStorage:
        """A RingStorage over slots ``start:stop`` of this one, sharing its memory (own cursor).

        DER keeps H1 and H2 in one storage so a mixed batch is gathered with one ``take``
        per field (see :class:`~der_ros.replay.double_replay.DoubleReplay`).
        """
        sub = object.__new__(RingStorage)
        sub.capacity = int(stop - start)
        sub.obs_shape = self.obs_shape
        sub.obs_dtype = self.obs_dtype
        for name in self.FIELDS:
            setattr(sub, name, getattr(self, name)[start:stop])
        sub.arrays_tuple = tuple(getattr(sub, name) for name in self.FIELDS)
        sub.cursor = 0
        sub.num_written = 0
        sub.offset = self.offset + int(start)
        sub._root = self._root
        sub._deferred = self._deferred
        return sub

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, f).nbytes for f in self.FIELDS)

    def next_slots(self, k: int) -> np.ndarray:
        """The next ``k`` ring slots (k <= capacity), advancing the cursor."""
        slots = (self.cursor + np.arange(k, dtype=np.int64)) % self.capacity
        self.cursor = (self.cursor + k) % self.capacity
        self.num_written += k
        return slots

    def skip(self, n: int) -> None:
        """Advance the ring as if ``n`` transitions had been written and overwritten at once
        (``add_batch`` with more rows than the capacity keeps the same slot layout as
        repeated ``add`` calls)."""
        self.cursor = (self.cursor + n) % self.capacity
        self.num_written += n

    def convert(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
    ) -> tuple[np.ndarray, ...]:
        """Check shapes and cast a batch of transitions to the storage dtypes.

        Observations may only be cast within their kind (float64 -> float32 is fine,
        float -> uint8 is refused: it would silently truncate pixel values).
        """
        obs = np.asarray(obs)
        next_obs = np.asarray(next_obs)
        k = obs.shape[0] if obs.ndim > 0 else -1
        for name, arr in (("obs", obs), ("next_obs", next_obs)):
            if arr.shape[1:] != self.obs_shape or arr.ndim != len(self.obs_shape) + 1:
                raise ValueError(f"{name} has shape {arr.shape}, expected (k, {', '.join(map(str, self.obs_shape))})")
            if arr.dtype != self.obs_dtype and not np.can_cast(arr.dtype, self.obs_dtype, casting="same_kind"):
                raise ValueError(f"{name} has dtype {arr.dtype}, cannot store it as {self.obs_dtype}")
        if next_obs.shape[0] != k:
            raise ValueError(f"next_obs has {next_obs.shape[0]} rows, obs has {k}")
        out = [obs.astype(self.obs_dtype, copy=False)]
        for name, arr, dt in (
            ("actions", actions, np.int64),
            ("rewards", rewards, np.float32),
            ("next_obs", next_obs, None),
            ("terminated", terminated, np.bool_),
            ("truncated", truncated, np.bool_),
        ):
            if dt is None:
                out.append(arr.astype(self.obs_dtype, copy=False))
                continue
            a = np.asarray(arr).reshape(-1)
            if a.shape[0] != k:
                raise ValueError(f"{name} has {a.shape[0]} entries, obs has {k}")
            if name == "rewards" and not np.all(np.isfinite(a)):
                raise ValueError(f"rewards contain non-finite values: {a[~np.isfinite(a)][:3]}")
            out.append(a.astype(dt, copy=False))
        return tuple(out)

    def append_batch(self, *batch: np.ndarray) -> np.ndarray:
        """Check and convert a batch (the arguments of :meth:`convert`) and write it at the next
        ring slots (FIFO); returns the slots written.

        With more rows than the capacity only the newest ``capacity`` survive, in the slots
        repeated single writes would have left them in.
        """
        fields = self.convert(*batch)
        k = fields[0].shape[0]
        if k > self.capacity:
            fields = tuple(f[k - self.capacity :] for f in fields)
            self.skip(k - self.capacity)
            k = self.capacity
        slots = self.next_slots(k)
        self.write(slots, fields)
        return slots

    def next_slot(self) -> int:
        """The next ring slot for one transition, advancing the cursor."""
        slot = self.cursor
        self.cursor = (slot + 1) % self.capacity
        self.num_written += 1
        return slot

    def _check_one(self, name: str, arr: Any) -> None:
        a = np.asarray(arr)
        if a.shape != self.obs_shape:
            raise ValueError(f"{name} has shape {a.shape}, expected {self.obs_shape}")
        if a.dtype != self.obs_dtype and not np.can_cast(a.dtype, self.obs_dtype, casting="same_kind"):
            raise ValueError(f"{name} has dtype {a.dtype}, cannot store it as {self.obs_dtype}")

    def put_one(self, slot: int, obs, action, reward, next_obs, terminated, truncated) -> None:
        """Check and write one transition to ``slot`` (the per-step path of ``add``; no batch arrays)."""
        if self._deferred[0] is not None:  # the deferred transition is completed before anything is written
            self.resolve()
        self._check_one("obs", obs)
        self._write_outcome(slot, reward, next_obs, terminated, truncated)  # checked before anything is written
        self.obs[slot] = obs
        self.actions[slot] = action

    def _write_outcome(self, slot: int, reward, next_obs, terminated, truncated) -> None:
        """Check, then write, what a step's outcome adds to (s, a): reward, next observation, flags."""
        self._check_one("next_obs", next_obs)
        reward = float(reward)
        if not math.isfinite(reward):
            raise ValueError(f"reward = {reward}, expected a finite number")
        self.next_obs[slot] = next_obs
        self.rewards[slot] = reward
        self.terminated[slot] = terminated
        self.truncated[slot] = truncated

    def write(self, slots: np.ndarray, fields: tuple[np.ndarray, ...]) -> None:
        """Write converted fields (as returned by :meth:`convert` or :meth:`gather`) to ``slots``."""
        if self._deferred[0] is not None:
            self.resolve()
        for dst, value in zip(self.arrays_tuple, fields):
            dst[slots] = value

    def gather(self, slots: np.ndarray) -> tuple[np.ndarray, ...]:
        """Copies of every field at ``slots`` (in :attr:`FIELDS` order); a deferred transition among
        them is completed first."""
        if self._deferred[0] is not None:
            self.resolve_among(slots)
        return tuple(src.take(slots, axis=0) for src in self.arrays_tuple)

    # deferred transition -------------------------------------------------------
    def defer(self, slot: int, complete: Callable[[], tuple[Any, ...]]) -> None:
        """Mark ``slot`` (written with placeholders) as waiting for its reward, next observation and
        flags: ``complete()`` returns ``(reward, next_obs, terminated, truncated)``.

        It is called at the first read of the slot (:meth:`gather`, :meth:`arrays`), before any other
        write, or by :meth:`resolve`, whichever comes first: whatever reads the storage sees the
        complete transition, so a learner can sample while the environment is still computing it
        (``train.env_process``) and get the same batch as if it had waited. One at a time: a pending
        one is completed first.
        """
        self.resolve()
        self._deferred[0] = (self._root, self.offset + int(slot), complete)

    def resolve(self) -> None:
        """Complete the deferred transition now (no-op when there is none)."""
        entry = self._deferred[0]
        if entry is None:
            return
        root, row, complete = entry
        self._deferred[0] = None
        root._write_outcome(row, *complete())

    def resolve_among(self, slots: np.ndarray) -> None:
        """:meth:`resolve` if the deferred transition is at one of ``slots`` (of this storage)."""
        entry = self._deferred[0]
        if entry is not None and bool((slots == entry[1] - self.offset).any()):
            self.resolve()

    # state -------------------------------------------------------------------
    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        if self._deferred[0] is not None:
            self.resolve()
        out = {f"{prefix}/{name}": getattr(self, name) for name in self.FIELDS}
        out[f"{prefix}/counters"] = np.array([self.cursor, self.num_written], dtype=np.int64)
        return out

    def set_arrays(self, arrays: dict[str, np.ndarray], prefix: str) -> None:
        self._deferred[0] = None  # the loaded state replaces whatever was waiting
        for name in self.FIELDS:
            getattr(self, name)[...] = arrays[f"{prefix}/{name}"]
        self.cursor, self.num_written = (int(x) for x in arrays[f"{prefix}/counters"])


def describe(capacity: int, obs_shape: Sequence[int], obs_dtype: np.dtype | str | type) -> str:
    """``capacity=..., obs_shape=..., obs_dtype=...`` for error messages."""
    shape = tuple(int(d) for d in obs_shape)
    per = 2 * math.prod(shape) * np.dtype(obs_dtype).itemsize
    return f"(capacity={capacity}, obs_shape={shape}, obs_dtype={np.dtype(obs_dtype)}, {per} obs bytes per transition)"
