"""Per-run scores that ``der train`` writes into ``summary.json`` (and the tables aggregate).

Paper section 4.1 (Table 1): the "max score" of a run is the highest moving average of 20
consecutive episode returns. It lives here, with the runner that reports it, rather than in
:mod:`der_ros.experiments.stats` (the multi-seed statistics), so the training layer does not
depend on the experiment layer above it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["moving_average", "max_moving_average"]


def moving_average(returns: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """Trailing means of ``window`` consecutive values (length n - window + 1; empty if n < window)."""
    r = np.asarray(returns, dtype=np.float64)
    if window < 1:
        raise ValueError(f"window = {window}, expected >= 1")
    if r.size < window:
        return np.empty(0, dtype=np.float64)
    c = np.concatenate([[0.0], np.cumsum(r)])
    return (c[window:] - c[:-window]) / window


def max_moving_average(returns: Sequence[float] | np.ndarray, window: int = 20) -> float:
    """The paper's "max score": highest mean of ``window`` consecutive episode returns.

    A run with fewer than ``window`` episodes scores the mean of all of them.
    """
    r = np.asarray(returns, dtype=np.float64)
    if r.size == 0:
        return math.nan
    if r.size < window:
        return float(r.mean())
    return float(moving_average(r, window).max())
