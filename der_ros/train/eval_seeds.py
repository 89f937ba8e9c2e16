"""The seed sets of training and evaluation, kept apart.

Every result we publish is the greedy policy run on **evaluation seeds** that no training run ever
uses (docs/evaluation.md):

* Training runs use seeds below :data:`TRAINING_SEED_LIMIT` (run seeds, and the environment seeds
  derived from them, see :func:`training_env_seed`).
* Report evaluations use ``EVAL_SEED_BASE + k``; tuning (any choice of settings, e.g. the
  gap-acceptance rule's thresholds) uses ``TUNING_EVAL_SEED_BASE + k``. The three sets are
  disjoint, and :func:`check_disjoint` asserts it wherever seeds meet.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from der_ros.configuration import ConfigError

__all__ = [
    "EVAL_SEED_BASE",
    "TUNING_EVAL_SEED_BASE",
    "TRAINING_SEED_LIMIT",
    "evaluation_seeds",
    "check_training_seed",
    "check_disjoint",
    "training_env_seed",
]

#: Training runs and the environment seeds derived from them are below this.
TRAINING_SEED_LIMIT = 1_000_000_000
#: Report evaluation seeds: EVAL_SEED_BASE + k.
EVAL_SEED_BASE = 1_000_000_000
#: Evaluation seeds of tuning runs and of the baselines' tuning: TUNING_EVAL_SEED_BASE + k.
TUNING_EVAL_SEED_BASE = 1_500_000_000
_SEED_SPAN = 500_000_000


def evaluation_seeds(n: int, base: int = EVAL_SEED_BASE) -> list[int]:
    """The first ``n`` evaluation seeds of the set starting at ``base``."""
    if base not in (EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE):
        raise ConfigError(
            f"eval_seed_base = {base!r}, expected {EVAL_SEED_BASE} (report) or {TUNING_EVAL_SEED_BASE} (tuning)"
        )
    if not 0 <= n <= _SEED_SPAN:
        raise ConfigError(f"evaluation episodes = {n!r}, expected 0..{_SEED_SPAN}")
    return list(range(base, base + n))


def check_training_seed(seed: int, what: str = "train.seed") -> int:
    """``seed`` if it is a valid training seed (below :data:`TRAINING_SEED_LIMIT`), else ConfigError."""
    if not 0 <= int(seed) < TRAINING_SEED_LIMIT:
        raise ConfigError(
            f"{what} = {seed!r}, expected 0 <= seed < {TRAINING_SEED_LIMIT} (seeds from {TRAINING_SEED_LIMIT} on "
            "are reserved for evaluation episodes)"
        )
    return int(seed)


def check_disjoint(training: Iterable[int], evaluation: Iterable[int]) -> None:
    """Raise if any evaluation seed is also a training seed, or lies in the training range."""
    train_set = {int(s) for s in training}
    eval_set = {int(s) for s in evaluation}
    shared = sorted(train_set & eval_set)
    if shared:
        raise ValueError(f"evaluation seeds {shared[:5]} are also training seeds")
    low = [s for s in eval_set if s < TRAINING_SEED_LIMIT]
    if low:
        raise ValueError(f"evaluation seeds {sorted(low)[:5]} lie in the training range (< {TRAINING_SEED_LIMIT})")
    high = [s for s in train_set if s >= TRAINING_SEED_LIMIT]
    if high:
        raise ValueError(f"training seeds {sorted(high)[:5]} lie in the evaluation range (>= {TRAINING_SEED_LIMIT})")


def training_env_seed(run_seed: int, step: int) -> int:
    """Environment seed for a training run restarted at ``step`` (resume): in the training range."""
    seq = np.random.SeedSequence([int(run_seed), int(step)])
    return int(seq.generate_state(1, dtype=np.uint64)[0] % TRAINING_SEED_LIMIT)
