"""ReplayConfig: which replay buffer the learner uses and its parameters.

Batch-size dependent defaults (``h2_capacity``, ``h2_min_size``) are resolved and checked
by :func:`der_ros.replay.factory.make_replay`, which knows the batch size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from der_ros.configuration import ConfigError, param

__all__ = ["ReplayConfig", "MAX_LOG_WEIGHT_LIMIT"]

#: float64 overflows at exp(709.78); the H2 sum tree holds N2 values up to exp(max_log_weight)
MAX_LOG_WEIGHT_LIMIT = 700.0


@dataclass
class ReplayConfig:
    """Replay buffer selection and parameters (uniform DQN, PER, or DER)."""

    kind: str = param(
        "der",
        "replay kind: 'uniform' (plain DQN), 'per' (proportional prioritized replay, Schaul et al. 2015) "
        "or 'der' (double experience replay, paper section 3)",
        choices=("uniform", "per", "der"),
    )
    capacity: int = param(
        50_000,
        "capacity of the main buffer: N1 of H1 for 'der' (paper: 50,000), the whole buffer otherwise",
        low=1,
    )
    alpha: float = param(0.6, "PER: priority exponent, priority = (|delta| + per_eps)^alpha", low=0.0, high=1.0)
    beta0: float = param(
        0.4, "PER: initial importance-sampling exponent beta, annealed linearly to 1", low=0.0, high=1.0
    )
    beta_steps: int = param(
        100_000, "PER: number of sample() calls over which beta goes from beta0 to 1 (0 = beta is 1 at once)", low=0
    )
    per_eps: float = param(
        1e-6, "PER: added to |delta| so no transition gets zero priority", low=0.0, low_inclusive=False
    )
    lam: float = param(
        0.5,
        "DER: lambda, fraction of every batch taken from H2 once H2 is ready: round(lambda * B) rows "
        "(0 = plain uniform DQN, 1 = only H2)",
        low=0.0,
        high=1.0,
    )
    h2_capacity: int | None = param(
        None, "DER: capacity N2 of H2 (null = 100 x batch size, as in the paper)", low=1
    )
    h2_min_size: int | None = param(
        None,
        "DER: H2 is sampled only once it holds at least this many transitions; until then batches come "
        "from H1 only (null = batch size)",
        low=1,
    )
    p_promote: float = param(
        1.0,
        "DER: probability that a transition sampled from H1 and used in a gradient step is put into H2",
        low=0.0,
        high=1.0,
    )
    promote_mode: str = param(
        "copy",
        "DER: 'copy' (default, every shipped config) keeps a promoted transition in H1 as well; 'move' removes it "
        "from H1, as the paper words it ('transitions move to H2') and the authors' code does (it pops from H1, "
        "but trains once per episode). Trained every step, 'move' drains H1: about (1 - lambda) x batch "
        "transitions leave per gradient step while one arrives, so N1 = 50,000 means nothing",
        choices=("move", "copy"),
    )
    h2_eviction: str = param(
        "fifo",
        "DER: which H2 entry a promotion replaces when H2 is full: 'fifo' the oldest entry, "
        "'min_weight' the entry with the smallest weight p (the most replayed, p close to 1)",
        choices=("fifo", "min_weight"),
    )
    eq3_sum: str = param(
        "h2",
        "DER: the sum in eq. 3, w = delta^2 / sum_n delta_n^2, runs over the batch's H2 transitions ('h2') "
        "or over the whole batch ('batch')",
        choices=("h2", "batch"),
    )
    max_log_weight: float = param(
        50.0,
        "DER: cap on log p of an H2 entry (log p = |delta| at promotion), so p = e^|delta| stays finite; "
        "an entry at the cap is e^50 ~ 5e21 times likelier than one at p = 1",
        low=0.0,
        high=MAX_LOG_WEIGHT_LIMIT,
        low_inclusive=False,
    )

    def check(self) -> None:
        """Cross-field rules of H2's sizes (checked again by the factory once the batch size fills
        in the defaults)."""
        if self.h2_capacity is not None and self.h2_min_size is not None and self.h2_min_size > self.h2_capacity:
            raise ConfigError(
                f"h2_min_size = {self.h2_min_size}, expected <= h2_capacity ({self.h2_capacity}); "
                "H2 would never become ready"
            )
        if self.h2_capacity is not None and self.max_log_weight > MAX_LOG_WEIGHT_LIMIT - math.log(self.h2_capacity):
            raise ConfigError(
                f"max_log_weight = {self.max_log_weight}, expected <= {MAX_LOG_WEIGHT_LIMIT} - ln(h2_capacity) "
                f"= {MAX_LOG_WEIGHT_LIMIT - math.log(self.h2_capacity):.1f} (the H2 weight sum must stay finite)"
            )
