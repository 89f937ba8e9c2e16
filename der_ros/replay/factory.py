"""The table of replay kinds: build the buffer a :class:`ReplayConfig` describes, or load a saved one.

This is where the batch-size dependent defaults of DER are resolved (the paper's
"N_2 = batch size x 100" and "H_2 ... an adequate amount of transitions to train" =
one batch) and where the rules that need the batch size are checked. The kinds are listed
here, in :data:`REPLAY_KINDS`, rather than registered by the classes on import: the base
module stays free of its subclasses (as TorchRL keeps ``samplers/base.py`` free of strategies).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from der_ros.configuration import ConfigError, validate
from der_ros.replay._numba import HAVE_NUMBA
from der_ros.replay.base import ReplayBuffer
from der_ros.replay.config import ReplayConfig
from der_ros.replay.double_replay import DoubleReplay
from der_ros.replay.prioritized import PrioritizedReplay
from der_ros.replay.storage import check_memory, describe, storage_bytes
from der_ros.replay.uniform import UniformReplay

__all__ = ["REPLAY_KINDS", "make_replay", "load_replay", "resolve_h2", "check_replay_memory", "warm_up_kernels"]

#: ``ReplayConfig.kind`` (also the ``kind`` saved with a buffer's state) -> class
REPLAY_KINDS: dict[str, type[ReplayBuffer]] = {cls.kind: cls for cls in (UniformReplay, PrioritizedReplay, DoubleReplay)}


def resolve_h2(cfg: ReplayConfig, batch_size: int) -> tuple[int, int]:
    """(h2_capacity, h2_min_size) with the defaults filled in: 100 x B and B."""
    n2 = cfg.h2_capacity if cfg.h2_capacity is not None else 100 * batch_size
    k = cfg.h2_min_size if cfg.h2_min_size is not None else batch_size
    return int(n2), int(k)


def check_replay_memory(
    cfg: ReplayConfig,
    obs_shape: Sequence[int],
    obs_dtype: np.dtype | str | type,
    batch_size: int,
    available_bytes: int | None = None,
) -> None:
    """Raise :class:`~der_ros.replay.storage.ReplayMemoryError` if the buffer ``cfg`` describes would not
    fit, without allocating it (``der graph`` checks the agent's replay before any process starts)."""
    needed = storage_bytes(cfg.capacity, obs_shape, obs_dtype)
    what = describe(cfg.capacity, obs_shape, obs_dtype)
    if cfg.kind == "der":
        n2, _k = resolve_h2(cfg, batch_size)
        needed += storage_bytes(n2, obs_shape, obs_dtype)
        what = f"H1 {what} + H2 (h2_capacity={n2})"
    check_memory(needed, what, available_bytes)


def make_replay(
    cfg: ReplayConfig,
    obs_shape: Sequence[int],
    obs_dtype: np.dtype | str | type,
    batch_size: int,
    seed: int | None = 0,
    available_bytes: int | None = None,
) -> ReplayBuffer:
    """The replay buffer for ``cfg``; raises :class:`ConfigError` naming the field and value
    for bad parameters, including a batch larger than a capacity."""
    validate(cfg, "replay")
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ConfigError(f"replay: batch_size = {batch_size!r}, expected an integer >= 1")
    batch_size = int(batch_size)
    if batch_size > cfg.capacity:
        raise ConfigError(f"replay: batch_size = {batch_size}, expected <= capacity ({cfg.capacity})")
    if cfg.kind == "uniform":
        return UniformReplay(cfg.capacity, obs_shape, obs_dtype, seed=seed, available_bytes=available_bytes)
    if cfg.kind == "per":
        warm_up_kernels()
        return PrioritizedReplay(
            cfg.capacity,
            obs_shape,
            obs_dtype,
            alpha=cfg.alpha,
            beta0=cfg.beta0,
            beta_steps=cfg.beta_steps,
            eps=cfg.per_eps,
            seed=seed,
            available_bytes=available_bytes,
        )
    warm_up_kernels()
    n2, k = resolve_h2(cfg, batch_size)
    if batch_size > n2:
        raise ConfigError(f"replay: batch_size = {batch_size}, expected <= h2_capacity ({n2})")
    resolved = dataclasses.replace(cfg, h2_capacity=n2, h2_min_size=k)
    return DoubleReplay(resolved, obs_shape, obs_dtype, seed=seed, available_bytes=available_bytes)


_kernels_warm = False


def warm_up_kernels() -> None:
    """Load the compiled sum-tree and DER kernels now, once per process, by running tiny buffers of
    every prioritized kind through add / sample / update_priorities.

    numba loads a cached kernel at its first call, about 0.5 s for the replay's kernels: without
    this, that stall fell on the first gradient step of every run (and into the timed loop of
    ``bench/train_loop.py``). Nothing of the tiny buffers is kept; no RNG of the caller is used.
    """
    global _kernels_warm
    if _kernels_warm or not HAVE_NUMBA:
        return
    _kernels_warm = True
    rng = np.random.default_rng(0)
    small = dict(capacity=64, h2_capacity=16, h2_min_size=4, lam=0.5)
    buffers: list[ReplayBuffer] = [PrioritizedReplay(64, (1,), np.float32, seed=0)]
    for mode in ("copy", "move"):
        buffers.append(DoubleReplay(ReplayConfig(kind="der", promote_mode=mode, **small), (1,), np.float32, seed=0))
    obs = np.zeros(1, dtype=np.float32)
    for buf in buffers:
        for _ in range(32):
            buf.add(obs, 0, 0.0, obs, False, False)
        for _ in range(3):
            batch = buf.sample(8)
            buf.update_priorities(batch.indices, rng.standard_normal(8))


def load_replay(path: str | os.PathLike[str]) -> ReplayBuffer:
    """Rebuild a buffer written by :meth:`ReplayBuffer.save`; sampling continues identically."""
    with np.load(Path(path), allow_pickle=False) as data:
        state = {k: data[k] for k in data.files}
    kind = str(state["kind"][()])
    if kind not in REPLAY_KINDS:
        raise ValueError(f"{path}: unknown replay kind {kind!r}; expected one of {sorted(REPLAY_KINDS)}")
    buf = REPLAY_KINDS[kind].from_ctor_kwargs(json.loads(str(state["ctor"][()])))
    buf.load_state_dict(state)
    return buf
