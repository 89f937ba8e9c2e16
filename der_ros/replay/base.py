"""The replay buffer contract shared by every sampler (see docs/architecture.md).

A buffer is storage + sampler: :class:`~der_ros.replay.storage.RingStorage` holds the
transitions, the subclass decides which slots a batch reads. Every kind has the same
methods -- ``update_priorities`` is a no-op where it means nothing -- so the learner never
special-cases the buffer it was given. The checks every kind applies at sample and update
time live here too; the table of kinds and loading from disk are in
:mod:`der_ros.replay.factory` (a base module does not know its subclasses).

State is a flat ``dict[str, np.ndarray]`` (keys like ``"h1/obs"``), which :meth:`save`
writes as one ``.npz`` without pickling anything (``allow_pickle=False`` on load).
"""

from __future__ import annotations

import json
import os
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np

from der_ros.configuration import ConfigError

if TYPE_CHECKING:
    from der_ros.replay.storage import RingStorage

__all__ = ["Batch", "ReplayBuffer", "STATE_FORMAT", "check_batch_size", "check_td_errors"]

#: bumped whenever the on-disk layout changes incompatibly
STATE_FORMAT = 1


class Batch(NamedTuple):
    """One sampled minibatch. Row i of every array is the same transition."""

    obs: np.ndarray  # (B, *obs_shape), storage dtype (uint8 frames stay uint8)
    actions: np.ndarray  # (B,) int64
    rewards: np.ndarray  # (B,) float32
    next_obs: np.ndarray  # (B, *obs_shape)
    terminated: np.ndarray  # (B,) bool -- cuts the bootstrap
    truncated: np.ndarray  # (B,) bool -- never cuts the bootstrap
    indices: np.ndarray  # (B,) int64 opaque handles for update_priorities
    weights: np.ndarray  # (B,) float32 importance weights; 1.0 where the method has none
    source: np.ndarray  # (B,) uint8: 0 = main/H1, 1 = H2


def check_batch_size(batch_size: int, capacity: int, size: int) -> None:
    """Sample-time guard shared by every buffer: 1 <= batch_size <= capacity and <= current size."""
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ConfigError(f"batch_size = {batch_size!r}, expected an integer >= 1")
    if batch_size > capacity:
        raise ConfigError(f"batch_size = {batch_size}, expected <= replay capacity ({capacity})")
    if batch_size > size:
        raise ConfigError(
            f"batch_size = {batch_size}, expected <= current replay size ({size}); "
            "wait until the buffer holds at least one batch (learning_starts)"
        )


def check_td_errors(indices: np.ndarray, td_errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 indices and float64 TD errors of the same length; non-finite TD errors raise ValueError."""
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    td = np.asarray(td_errors, dtype=np.float64).reshape(-1)
    if idx.shape != td.shape:
        raise ValueError(f"update_priorities: {idx.size} indices but {td.size} TD errors")
    # one reduction instead of isfinite(...).all(): a nan/inf element makes the sum nan/inf
    # (a sum that overflows from finite values only triggers the exact check below)
    if td.size and not np.isfinite(td.sum()):
        bad = np.flatnonzero(~np.isfinite(td))
        if bad.size:
            raise ValueError(
                f"update_priorities: {bad.size} non-finite TD error(s), first at batch row {bad[0]}: {td[bad[0]]}; "
                "the learner has diverged"
            )
    return idx, td


def rng_state_to_array(rng: np.random.Generator) -> np.ndarray:
    """The generator state as a 0-d unicode array (JSON keeps the 128-bit PCG64 integers exact)."""
    return np.array(json.dumps(rng.bit_generator.state))


def rng_from_array(arr: np.ndarray) -> np.random.Generator:
    state = json.loads(str(arr[()]))
    bitgen = getattr(np.random, state["bit_generator"])()
    bitgen.state = state
    return np.random.Generator(bitgen)


class ReplayBuffer(ABC):
    """Common interface of the uniform, prioritized and double replay buffers."""

    #: stable name used in saved files and ``ReplayConfig.kind``
    kind: ClassVar[str] = ""
    #: whether ``sample()`` returns importance weights other than 1 (PER); the learner skips the
    #: multiplications by 1.0 otherwise (exact: the loss and gradient are bit for bit the same)
    importance_weighted: ClassVar[bool] = False

    # ------------------------------------------------------------------ writing
    def add(
        self,
        obs: np.ndarray,
        action: int,
        reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        truncated: bool,
    ) -> None:
        """Store one transition (s_k, a_k, r_{k+1}, s_{k+1}, terminated_{k+1}, truncated_{k+1})."""
        self.add_batch(
            np.asarray(obs)[None],
            np.asarray([action]),
            np.asarray([reward]),
            np.asarray(next_obs)[None],
            np.asarray([terminated]),
            np.asarray([truncated]),
        )

    def add_deferred(self, obs: np.ndarray, action: int, complete: Callable[[], tuple[Any, ...]]) -> None:
        """Store (s_k, a_k) now and the rest of the transition when it is known.

        ``complete()`` returns ``(reward, next_obs, terminated, truncated)``; it is called when a
        batch first reads the transition, before anything else is written, when the state is
        saved, or at :meth:`resolve_deferred`, whichever comes first. Sampling, priorities and
        promotions do not depend on those four fields until a batch holds the transition, so a
        learner can take its gradient step while the environment still computes them and get,
        bit for bit, the step it would have taken after an :meth:`add` (``train.env_process``).
        """
        self.resolve_deferred()
        self.add(obs, action, 0.0, obs, False, False)
        storage, slot = self._newest_slot()
        storage.defer(slot, complete)

    def resolve_deferred(self) -> None:
        """Complete the transition of :meth:`add_deferred` now, if it still waits."""
        self._newest_slot()[0].resolve()

    @abstractmethod
    def _newest_slot(self) -> tuple[RingStorage, int]:
        """The storage :meth:`add` writes to and the slot of the last transition it wrote."""

    @abstractmethod
    def add_batch(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
    ) -> None:
        """Store many transitions at once (leading axis = transition), in order, as if by
        repeated :meth:`add` calls. Used to fill buffers from recorded bags."""

    # ------------------------------------------------------------------ sampling
    @abstractmethod
    def sample(self, batch_size: int) -> Batch:
        """Draw one minibatch of ``batch_size`` transitions."""

    @abstractmethod
    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """Report the TD errors of the batch just used in a gradient step (no-op for uniform)."""

    @abstractmethod
    def __len__(self) -> int:
        """Number of transitions that can currently be sampled."""

    @abstractmethod
    def stats(self) -> dict[str, float]:
        """Metrics with stable names (``replay/size``, ...)."""

    # ------------------------------------------------------------------ state
    @abstractmethod
    def _ctor_kwargs(self) -> dict[str, Any]:
        """JSON-able constructor arguments, saved with the state (``"ctor"``)."""

    @classmethod
    def from_ctor_kwargs(cls, kwargs: dict[str, Any]) -> ReplayBuffer:
        """An empty buffer built from saved :meth:`_ctor_kwargs` (memory was checked when it was
        first built), ready for :meth:`load_state_dict`."""
        return cls(**kwargs, check_memory=False)

    @abstractmethod
    def _arrays(self) -> dict[str, np.ndarray]:
        """Every array and counter that makes up the state (besides rng and ctor arguments)."""

    @abstractmethod
    def _set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """Inverse of :meth:`_arrays`; shapes/dtypes were already checked."""

    def state_dict(self, copy: bool = True) -> dict[str, np.ndarray]:
        """Everything needed to continue identically: data, trees, counters, RNG state.

        With ``copy=True`` the arrays are copies, so the dict stays valid while the buffer
        keeps changing. ``copy=False`` returns views of the buffer's own arrays (no second
        copy of a multi-GB Atari replay when a checkpoint is written at once); they change
        with the buffer.
        """
        state = {
            "format": np.array(STATE_FORMAT, dtype=np.int64),
            "kind": np.array(self.kind),
            "ctor": np.array(json.dumps(self._ctor_kwargs())),
            "rng": rng_state_to_array(self._rng),
        }
        for key, arr in self._arrays().items():
            state[key] = np.array(arr, copy=True) if copy else arr
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict`; the buffer must have been built with the same arguments."""
        kind = str(np.asarray(state.get("kind", ""))[()])
        if kind != self.kind:
            raise ValueError(f"replay state is of kind {kind!r}, this buffer is {self.kind!r}")
        fmt = int(np.asarray(state.get("format", -1)))
        if fmt != STATE_FORMAT:
            raise ValueError(f"replay state format {fmt}, expected {STATE_FORMAT}")
        ctor = json.loads(str(np.asarray(state["ctor"])[()]))
        mine = json.loads(json.dumps(self._ctor_kwargs()))
        if ctor != mine:
            diff = sorted(k for k in set(ctor) | set(mine) if ctor.get(k) != mine.get(k))
            raise ValueError(
                "replay state was saved by a buffer with different arguments: "
                + ", ".join(f"{k} = {ctor.get(k)!r} (this buffer: {mine.get(k)!r})" for k in diff)
            )
        current = self._arrays()
        arrays: dict[str, np.ndarray] = {}
        for key, ref in current.items():
            if key not in state:
                raise ValueError(f"replay state lacks the array {key!r}")
            arr = np.asarray(state[key])
            if arr.shape != ref.shape or arr.dtype != ref.dtype:
                raise ValueError(
                    f"replay state array {key!r} has shape {arr.shape} dtype {arr.dtype}, "
                    f"expected {ref.shape} {ref.dtype}"
                )
            arrays[key] = arr
        self._set_arrays(arrays)
        self._rng = rng_from_array(np.asarray(state["rng"]))

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`state_dict` to ``path`` (.npz) atomically: temp file in the same
        directory, fsync, then ``os.replace`` -- a crash never leaves a half-written file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **self.state_dict(copy=False))
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            raise
