"""Scores and confidence intervals for the multi-seed tables.

* Paper section 4.1 (Table 1): "max score" = the highest moving average of 20 consecutive episode
  returns; "average score" = the mean return over all episodes of the run.
* Paper section 5 (Table 2): averages over 100 episode returns.
* Across seeds we report the mean with a 95% percentile-bootstrap confidence interval of the mean
  (fixed seed, 10,000 resamples by default), so the interval is reproducible bit for bit.
* Two policies on the same traffic situations: the exact two-sided sign test on the situations
  where they differ (:func:`sign_test_p`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from der_ros.train.scores import max_moving_average, moving_average

__all__ = [
    "CI",
    "bootstrap_ci",
    "bootstrap_band",
    "moving_average",
    "max_moving_average",
    "average_score",
    "mean_of_last",
    "curve_on_grid",
    "sign_test_p",
]


@dataclass(frozen=True)
class CI:
    """A mean and its confidence interval over ``n`` values."""

    mean: float
    low: float
    high: float
    n: int

    def format(self, digits: int = 2) -> str:
        """'229.30 ± 12.40' style (half width of the interval; the interval may be asymmetric)."""
        if math.isnan(self.mean):
            return "n/a"
        half = max(self.high - self.mean, self.mean - self.low)
        return f"{self.mean:.{digits}f} ± {half:.{digits}f}"

    def format_cell(self, digits: int = 2) -> str:
        """Table cell: 'mean ± half-width [low, high]', or 'n/a' without data."""
        if math.isnan(self.mean):
            return "n/a"
        return f"{self.format(digits)} [{self.low:.{digits}f}, {self.high:.{digits}f}]"

    def format_interval(self, digits: int = 2) -> str:
        if math.isnan(self.mean):
            return "n/a"
        return f"{self.mean:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def bootstrap_ci(
    values: Sequence[float] | np.ndarray, confidence: float = 0.95, n_resamples: int = 10_000, seed: int = 0
) -> CI:
    """Percentile bootstrap CI of the mean of ``values``.

    Resamples ``values`` with replacement ``n_resamples`` times (numpy Generator seeded with
    ``seed``) and returns the (1-c)/2 and (1+c)/2 quantiles of the resampled means. One value gives
    a zero-width interval; no values give NaNs.
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    x = x[~np.isnan(x)]
    if x.size == 0:
        return CI(math.nan, math.nan, math.nan, 0)
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence = {confidence!r}, expected 0 < confidence < 1")
    mean = float(x.mean())
    if x.size == 1:
        return CI(mean, mean, mean, 1)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(n_resamples, x.size))
    means = x[idx].mean(axis=1)
    lo, hi = np.quantile(means, [(1.0 - confidence) / 2.0, (1.0 + confidence) / 2.0])
    return CI(mean, float(lo), float(hi), int(x.size))


def bootstrap_band(
    curves: np.ndarray, confidence: float = 0.95, n_resamples: int = 2_000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and bootstrap CI band of ``curves`` (seeds x points), resampling whole seeds.

    Points where some seeds are NaN use the seeds that have a value there.
    """
    c = np.asarray(curves, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"curves has shape {c.shape}, expected (seeds, points)")
    n = c.shape[0]
    with np.errstate(invalid="ignore"), _quiet_nan_warnings():
        mean = np.nanmean(c, axis=0)
        if n == 1:
            return mean, mean.copy(), mean.copy()
        rng = np.random.default_rng(seed)
        idx = rng.integers(0, n, size=(n_resamples, n))
        means = np.nanmean(c[idx], axis=1)  # (resamples, points)
        lo = np.nanquantile(means, (1.0 - confidence) / 2.0, axis=0)
        hi = np.nanquantile(means, (1.0 + confidence) / 2.0, axis=0)
    return mean, lo, hi


class _quiet_nan_warnings:
    def __enter__(self) -> None:
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: object) -> None:
        self._ctx.__exit__(*exc)


def sign_test_p(wins: int, losses: int) -> float:
    """Exact two-sided sign test: the chance of a split at least this uneven if either side were equally likely.

    ``wins`` and ``losses`` count the paired cases (ties left out) where the first policy does better /
    worse. ``P = min(1, 2 · P(Binomial(n, ½) ≤ min(wins, losses)))``, n = wins + losses; 1.0 when n = 0.
    """
    if wins < 0 or losses < 0:
        raise ValueError(f"sign_test_p: wins and losses must be counts >= 0, got wins={wins}, losses={losses}")
    n, k = wins + losses, min(wins, losses)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2.0 * tail)


def average_score(returns: Sequence[float] | np.ndarray) -> float:
    """The paper's "average score": mean return over all episodes of a run."""
    r = np.asarray(returns, dtype=np.float64)
    return float(r.mean()) if r.size else math.nan


def mean_of_last(returns: Sequence[float] | np.ndarray, n: int = 100) -> float:
    """Mean of the last ``n`` episode returns (all of them if fewer)."""
    r = np.asarray(returns, dtype=np.float64)
    return float(r[-n:].mean()) if r.size else math.nan


def curve_on_grid(
    episode_steps: Sequence[float] | np.ndarray,
    returns: Sequence[float] | np.ndarray,
    grid: np.ndarray,
    window: int = 20,
) -> np.ndarray:
    """Learning curve of one run on a common step grid (Fig. 1 style).

    Value at grid step g = mean return of the last ``window`` episodes finished at or before g
    (fewer while fewer exist); NaN before the first episode ends.
    """
    s = np.asarray(episode_steps, dtype=np.float64)
    r = np.asarray(returns, dtype=np.float64)
    out = np.full(len(grid), np.nan)
    if r.size == 0:
        return out
    c = np.concatenate([[0.0], np.cumsum(r)])
    k = np.searchsorted(s, grid, side="right")  # episodes finished by each grid step
    have = k > 0
    lo = np.maximum(k - window, 0)
    out[have] = (c[k[have]] - c[lo[have]]) / (k[have] - lo[have])
    return out
