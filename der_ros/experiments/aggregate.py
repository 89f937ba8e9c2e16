"""Aggregates over training seeds, as the RL-evaluation literature recommends (rliable).

Agarwal et al., "Deep RL at the edge of the statistical precipice" (NeurIPS 2021): with a handful
of seeds, report the **interquartile mean** (IQM, the 25% trimmed mean) with **stratified
bootstrap** 95% confidence intervals, and compare methods by the **probability of improvement**
P(X > Y) with its CI; say "better" only when that CI excludes 0.5. We use the authors' package
``rliable`` for all three (one task per table, so "stratified" = resampling seeds), with a
fixed random state so that a table is reproducible bit for bit.

Per-run scores come from the run directories: the final greedy evaluation (``evaluation.json``),
the periodic ones (``evaluations.csv``) and the training episodes (``episodes.csv``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.train.eval_result import EVALUATIONS_CSV, FINAL_EVAL_JSON, EvalResult, read_evaluations

__all__ = [
    "Interval",
    "iqm_interval",
    "mean_interval",
    "probability_of_improvement",
    "final_evaluation",
    "evaluation_curve",
    "significance_sentence",
    "verdict",
    "iqm",
    "iqm_band",
    "per_seed_lists",
    "BOOTSTRAP_REPS",
]

#: Bootstrap resamples for every interval. rliable's default is 50,000, but its resampling runs one
#: Python call per resample (~1-2 ms each here), and a table needs ~40 intervals per network; with
#: 2,000 the interval ends move by about 0.01 on a [0, 1] scale between resample counts (checked
#: against 20,000), which is below the precision we print. The random state is fixed.
BOOTSTRAP_REPS = 2_000
_SEED = 0


@dataclass(frozen=True)
class Interval:
    """A point estimate with its 95% confidence interval."""

    value: float
    low: float
    high: float

    def format(self, digits: int = 3) -> str:
        if math.isnan(self.value):
            return "n/a"
        return f"{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"

    def to_list(self) -> list[float]:
        return [self.value, self.low, self.high]


_NAN = Interval(math.nan, math.nan, math.nan)


def _clean(scores: Sequence[float] | np.ndarray) -> np.ndarray:
    x = np.asarray(scores, dtype=np.float64).ravel()
    return x[~np.isnan(x)]


class _Quiet:
    """rliable passes a RandomState to arch, which warns that it will want a Generator one day, and it
    logs one absl INFO line per interval: both silenced. Its stratified bootstrap draws its indices from
    numpy's *global* random state (``np.random.choice``), whatever ``random_state`` says: that state is
    seeded here and restored on exit, so an interval is the same on every rerun of a report."""

    def __init__(self) -> None:
        import logging
        import warnings

        logging.getLogger("absl").setLevel(logging.WARNING)
        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        warnings.simplefilter("ignore", FutureWarning)
        self._state = np.random.get_state()
        np.random.seed(_SEED)

    def __exit__(self, *exc: Any) -> None:
        np.random.set_state(self._state)
        self._warnings.__exit__(*exc)


def _quiet() -> _Quiet:
    return _Quiet()


def _interval(scores: np.ndarray, func: Any, reps: int) -> Interval:
    from rliable import library as rly

    if scores.size == 0:
        return _NAN
    point = float(func(scores[:, None]))
    if scores.size == 1:
        return Interval(point, point, point)
    ctx = _quiet()
    try:
        _, cis = rly.get_interval_estimates(
            {"x": scores[:, None]}, lambda s: np.array([func(s)]), reps=reps,
            random_state=np.random.RandomState(_SEED),
        )  # fmt: skip
    finally:
        ctx.__exit__(None, None, None)
    lo, hi = cis["x"][:, 0]
    return Interval(point, float(lo), float(hi))


def iqm_interval(scores: Sequence[float] | np.ndarray, reps: int = BOOTSTRAP_REPS) -> Interval:
    """IQM over seeds with its stratified-bootstrap 95% CI (rliable)."""
    from rliable import metrics

    return _interval(_clean(scores), metrics.aggregate_iqm, reps)


def mean_interval(scores: Sequence[float] | np.ndarray, reps: int = BOOTSTRAP_REPS) -> Interval:
    """Mean over seeds with its stratified-bootstrap 95% CI (rliable)."""
    from rliable import metrics

    return _interval(_clean(scores), metrics.aggregate_mean, reps)


def probability_of_improvement(
    x: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray, reps: int = BOOTSTRAP_REPS
) -> Interval:
    """P(X > Y) (ties count one half) of per-seed scores, with its bootstrap 95% CI (rliable)."""
    from rliable import library as rly
    from rliable import metrics

    a, b = _clean(x), _clean(y)
    if a.size == 0 or b.size == 0:
        return _NAN
    point = float(metrics.probability_of_improvement(a[:, None], b[:, None]))
    if a.size == 1 and b.size == 1:
        return Interval(point, point, point)
    ctx = _quiet()
    try:
        _, cis = rly.get_interval_estimates(
            {"xy": (a[:, None], b[:, None])}, metrics.probability_of_improvement, reps=reps,
            random_state=np.random.RandomState(_SEED),
        )  # fmt: skip
    finally:
        ctx.__exit__(None, None, None)
    lo, hi = cis["xy"][:, 0]
    return Interval(point, float(lo), float(hi))


#: fewer training seeds than this on either side: no verdict (a bootstrap over 2-4 seeds is not a CI)
MIN_SEEDS_FOR_VERDICT = 5


def verdict(poi: Interval, n: int = MIN_SEEDS_FOR_VERDICT) -> str | None:
    """What P(X > Y) and its 95% CI say: "better" if the whole CI lies above 0.5, "worse" if below,
    "indistinguishable" if it contains 0.5 (whatever the point estimate); None without data or with fewer
    than :data:`MIN_SEEDS_FOR_VERDICT` seeds on either side (``n`` = the smaller number of seeds)."""
    if math.isnan(poi.value) or n < MIN_SEEDS_FOR_VERDICT:
        return None
    if poi.low > 0.5:
        return "better"
    if poi.high < 0.5:
        return "worse"
    return "indistinguishable"


def significance_sentence(name_x: str, name_y: str, poi: Interval, metric: str, n: int = MIN_SEEDS_FOR_VERDICT) -> str:
    """One sentence that follows from P(X > Y) and its CI (better / worse / not distinguishable);
    ``n`` = the smaller number of seeds of the two."""
    if math.isnan(poi.value):
        return f"{name_x} vs {name_y}: no data."
    if n < MIN_SEEDS_FOR_VERDICT:
        return (f"{name_x} vs {name_y} on {metric}: P({name_x} > {name_y}) = {poi.format(2)}, from {n} seeds, "
                f"too few for a verdict (at least {MIN_SEEDS_FOR_VERDICT}).")
    word = verdict(poi, n)
    if word == "better":
        text = f"{name_x} is better than {name_y}"
    elif word == "worse":
        text = f"{name_x} is worse than {name_y}"
    else:
        text = f"{name_x} and {name_y} cannot be told apart"
    return f"{text} on {metric} (P({name_x} > {name_y}) = {poi.format(2)}; the CI {'excludes' if not poi.low <= 0.5 <= poi.high else 'includes'} 0.5)."


def iqm(values: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean along ``axis``: the mean of the middle 50% (scipy's 25% trimmed mean, as rliable)."""
    from scipy.stats import trim_mean

    return np.asarray(trim_mean(values, 0.25, axis=axis))


def iqm_band(curves: np.ndarray, reps: int = 2_000, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IQM over seeds of ``curves`` (seeds x points) with a bootstrap band (seeds resampled; vectorised).

    Used for the evaluation curves of the figures (rliable's per-point loop is too slow for
    hundreds of points); points where some seeds have no value use the seeds that do.
    """
    c = np.asarray(curves, dtype=np.float64)
    m = c.shape[1]
    point = np.full(m, np.nan)
    lo, hi = point.copy(), point.copy()
    for j in range(m):
        col = c[:, j]
        ok = ~np.isnan(col)
        if not ok.any():
            continue
        point[j] = float(iqm(col[ok]))
        if ok.sum() == 1:
            lo[j] = hi[j] = point[j]
            continue
        vals = col[ok]
        idx = np.random.default_rng(_SEED).integers(0, vals.size, size=(reps, vals.size))
        boot = iqm(vals[idx], axis=1)
        lo[j], hi[j] = np.quantile(boot, [(1 - confidence) / 2, (1 + confidence) / 2])
    return point, lo, hi


def final_evaluation(run_dir: str | Path) -> EvalResult | None:
    """The run's final greedy evaluation (``evaluation.json``), or None if it has none."""
    path = Path(run_dir) / FINAL_EVAL_JSON
    return EvalResult.load(path) if path.is_file() else None


def evaluation_curve(run_dir: str | Path) -> dict[str, np.ndarray]:
    """The run's periodic evaluations as columns (``evaluations.csv``), sorted by step."""
    return read_evaluations(Path(run_dir) / EVALUATIONS_CSV)


def per_seed_lists(values: Mapping[int, float], seeds: Sequence[int]) -> list[float]:
    """Values in the order of ``seeds`` (NaN where a seed has none)."""
    return [float(values.get(s, math.nan)) for s in seeds]
