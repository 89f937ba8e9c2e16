"""``der evaluate --traffic / --safety``: the env a trained run is evaluated in, and the bound it reports."""

from __future__ import annotations

import math

import pytest

from der_ros.configuration import ConfigError
from der_ros.experiments.evaluate_runs import evaluation_env, upper_bound_95
from der_ros.safety.config import SafetyConfig
from der_ros.train.config import EnvConfig

RING = "der_ros/LaneChangeRing-v0"


def ring_env(safety: SafetyConfig | None = None, **scenario: object) -> EnvConfig:
    return EnvConfig(id=RING, kwargs={"scenario": dict(scenario)}, safety=safety or SafetyConfig())


def test_other_traffic_keeps_the_runs_own_shield() -> None:
    shield = SafetyConfig(kind="rss", response_time=0.2)
    run = ring_env(shield, ring_outer_vehicles=[6, 10])
    dense = ring_env(None, ring_outer_vehicles=[10, 14])
    env = evaluation_env(run, dense)
    assert env.kwargs == dense.kwargs and env.safety == shield
    assert evaluation_env(run) == run


def test_the_shield_switched_off_and_on() -> None:
    shield = SafetyConfig(kind="rss", response_time=0.2)
    assert evaluation_env(ring_env(shield), safety="none").safety.kind == "none"
    assert evaluation_env(ring_env(shield), safety="rss").safety == shield  # the run's own parameters
    assert evaluation_env(ring_env(), safety="rss").safety == SafetyConfig(kind="rss")  # the defaults


def test_traffic_of_another_env_is_refused() -> None:
    with pytest.raises(ConfigError, match="env.id = 'CartPole-v1'"):
        evaluation_env(ring_env(), EnvConfig(id="CartPole-v1"))
    with pytest.raises(ConfigError, match="--safety = 'bogus'"):
        evaluation_env(ring_env(), safety="bogus")


@pytest.mark.parametrize("n", [300, 3000, 10000])
def test_zero_in_n_has_the_closed_form_bound(n: int) -> None:
    assert upper_bound_95(0, n) == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-9)
    assert upper_bound_95(0, 10000) <= 0.0003  # the "<= 0.03 %" needs 10,000 clean episodes


def test_the_bound_is_the_exact_binomial_one() -> None:
    # P(X <= k | n, bound) = 0.05 at the bound, and the bound grows with k
    for k, n in [(1, 1000), (3, 1000), (47, 30000), (1486, 3000)]:
        p = upper_bound_95(k, n)
        log_terms = [math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * math.log(p)
                     + (n - i) * math.log1p(-p) for i in range(k + 1)]  # fmt: skip
        cdf = sum(math.exp(t) for t in log_terms)
        assert cdf == pytest.approx(0.05, abs=1e-6) and p > k / n
    assert upper_bound_95(3, 1000) > upper_bound_95(1, 1000)
    assert upper_bound_95(5, 5) == 1.0 and math.isnan(upper_bound_95(0, 0))
