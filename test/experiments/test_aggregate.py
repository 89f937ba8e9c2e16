"""Aggregates over seeds (rliable): reproducible, and they do not disturb the caller's random state."""

from __future__ import annotations

import numpy as np
import pytest

from der_ros.experiments.aggregate import iqm_interval, mean_interval, probability_of_improvement

X = [0.93, 0.947, 0.97, 0.97, 0.983, 0.98, 0.96, 0.98, 0.957, 0.977]
Y = [0.987, 0.957, 0.97, 0.973, 0.957, 0.977, 0.98, 0.99, 0.95, 0.973]


def _all() -> list[list[float]]:
    return [iqm_interval(X).to_list(), mean_interval(X).to_list(), probability_of_improvement(Y, X, reps=500).to_list()]


@pytest.mark.slow
def test_intervals_do_not_depend_on_the_global_random_state_and_leave_it_alone() -> None:
    np.random.seed(1)
    first = _all()
    np.random.seed(12345)
    before = np.random.get_state()[1].copy()
    second = _all()
    after = np.random.get_state()[1]
    assert first == second  # rliable draws from numpy's global state; the report pins it
    assert np.array_equal(before, after)  # and gives the caller's state back
    lo, hi = first[0][1], first[0][2]
    assert lo < first[0][0] < hi and lo >= min(X) and hi <= max(X)
