"""Scores and confidence intervals for the multi-seed tables.

* Paper section 4.1 (Table 1): "max score" = the highest moving average of 20 consecutive episode
  returns; "average score" = the mean return over all episodes of the run.
* Paper section 5 (Table 2): averages over 100 episode returns.
* Across seeds we report the mean with a 95% percentile-bootstrap confidence interval of the mean
  (fixed seed, 10,000 resamples by default), so the interval is reproducible bit for bit.
* Two policies on the same traffic situations: a paired permutation test (sign flips) of the mean
  difference over situations (:func:`paired_permutation_p`).
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
    "paired_permutation_p",
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


def paired_permutation_p(diffs: Sequence[float] | np.ndarray, resamples: int = 100_000, seed: int = 0) -> float:
    """Two-sided paired permutation test (sign flips) that the mean of ``diffs`` is zero.

    ``diffs`` are paired differences, e.g. one per traffic situation: a method's success rate there
    minus a baseline's. Under the null each difference is as likely to have the other sign, so p is
    the share of sign assignments whose sum is at least as far from zero as the observed one. Zeros
    carry no information and are dropped. Up to 16 non-zero differences every assignment is counted
    (exact; ``n`` all of one sign give p = 2 / 2^n); above that ``resamples`` random ones, with the
    generator seeded so p is reproducible, and p = (hits + 1) / (resamples + 1). 1.0 without any
    non-zero difference.
    """
    if resamples < 1:
        raise ValueError(f"paired_permutation_p: resamples = {resamples!r}, expected >= 1")
    d = np.asarray(diffs, dtype=np.float64).ravel()
    if not np.all(np.isfinite(d)):
        raise ValueError("paired_permutation_p: diffs must be finite numbers")
    d = d[d != 0.0]
    n = d.size
    if n == 0:
        return 1.0
    observed = abs(float(d.sum()))
    tol = 1e-9 * float(np.abs(d).sum())  # sums equal to the observed one up to rounding count as hits
    if n <= _EXACT_FLIPS:
        signs = ((np.arange(2**n)[:, None] >> np.arange(n)) & 1) * 2 - 1
        return float(np.mean(np.abs(signs @ d) >= observed - tol))
    rng = np.random.default_rng(seed)
    hits = done = 0
    while done < resamples:
        m = min(10_000, resamples - done)
        signs = rng.integers(0, 2, size=(m, n)) * 2 - 1
        hits += int(np.count_nonzero(np.abs(signs @ d) >= observed - tol))
        done += m
    return (hits + 1) / (resamples + 1)


#: up to this many non-zero differences :func:`paired_permutation_p` counts every sign assignment
_EXACT_FLIPS = 16


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
