"""Double experience replay (paper section 3, Algorithm 1, eq. 3): split, warm-up, promotion,
eq. 3 on hand-computed numbers, H2 sampling frequencies, eviction, numerics, handles.

Transitions are identified by their reward (= running id). Statistical tests use fixed
seeds and chi-square at significance 1e-3.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from der_ros.replay.config import ReplayConfig
from der_ros.replay.double_replay import DoubleReplay, h2_split
from der_ros.replay.factory import make_replay

P_MIN = 1e-3


def fill(buf, n: int, start: int = 0) -> None:
    ids = np.arange(start, start + n)
    obs = np.stack([ids, -ids], axis=1).astype(np.float32)
    buf.add_batch(obs, ids % 3, ids.astype(np.float32), obs + 0.5, ids % 7 == 0, ids % 5 == 0)


def der(seed: int = 0, obs_shape: tuple[int, ...] = (2,), **fields) -> DoubleReplay:
    # 'move' unless a test asks for 'copy' (the library default): most rules below are about moving
    cfg = dict(kind="der", capacity=100, h2_capacity=50, lam=0.5, h2_min_size=1, promote_mode="move")
    cfg.update(fields)
    return DoubleReplay(ReplayConfig(**cfg), obs_shape, seed=seed)


def h1_ids(buf: DoubleReplay) -> set[int]:
    return set(buf.h1.rewards[buf.h1_live[: buf.h1_size]].astype(int).tolist())


def h2_ids(buf: DoubleReplay) -> list[int]:
    return buf.h2.rewards[: buf.h2_size].astype(int).tolist()


def h2_logw_by_id(buf: DoubleReplay) -> dict[int, float]:
    return dict(zip(h2_ids(buf), buf.h2_logw[: buf.h2_size].tolist()))


def promote(buf: DoubleReplay, ids_to_delta: dict[int, float], batch: int = 8) -> None:
    """Sample from H1 (warm-up phase) until every id in ids_to_delta was promoted with its delta."""
    todo = dict(ids_to_delta)
    for _ in range(10_000):
        if not todo:
            return
        b = buf.sample(batch)
        ids = b.rewards.astype(int)
        keep = np.isin(ids, list(todo)) & (b.source == 0)
        if keep.any():
            td = np.array([todo.get(i, 0.0) for i in ids[keep]])
            buf.update_priorities(b.indices[keep], td)
            for i in ids[keep]:
                todo.pop(int(i), None)
    raise AssertionError("could not promote " + str(todo))


# ---------------------------------------------------------------- batch split
@pytest.mark.parametrize("lam", [0.0, 0.1, 0.25, 0.5, 0.9, 1.0])
@pytest.mark.parametrize("batch", [1, 7, 32, 33])
def test_exact_lambda_split_in_every_batch(lam, batch):
    buf = der(capacity=400, h2_capacity=200, lam=lam, h2_min_size=batch, promote_mode="copy", seed=batch)
    fill(buf, 400)
    n2 = math.floor(lam * batch + 0.5)
    ready = False
    for _ in range(60):
        b = buf.sample(batch)
        expect = n2 if ready else 0
        np.testing.assert_array_equal(b.source, np.r_[np.zeros(batch - expect), np.ones(expect)].astype(np.uint8))
        assert buf.stats()["replay/h2_fraction"] == pytest.approx(expect / batch)
        np.testing.assert_array_equal(b.weights, 1.0)  # no importance sampling in DER
        buf.update_priorities(b.indices, np.ones(batch))
        ready = buf.h2_size >= batch
    assert ready or (lam == 0.0 and buf.h2_size == 0)  # lambda = 0 promotes nothing


def test_h2_split_rounds_half_up():
    assert [h2_split(0.5, b) for b in (1, 3, 5, 127)] == [1, 2, 3, 64]
    assert h2_split(0.1, 128) == 13 and h2_split(0.9, 128) == 115 and h2_split(0.0, 128) == 0
    assert h2_split(1.0, 33) == 33


def test_warm_up_h1_only_until_h2_min_size():
    buf = der(h2_min_size=10, lam=0.5)
    fill(buf, 100)
    seen_split = False
    while not seen_split:
        size_before = buf.h2_size
        b = buf.sample(4)
        if size_before < 10:
            assert (b.source == 0).all()
        else:
            assert b.source.sum() == 2
            seen_split = True
        buf.update_priorities(b.indices, np.ones(4))
    assert buf.h2_size >= 10


# ---------------------------------------------------------------- promotion
def test_promotion_move_sets_weight_and_removes_from_h1():
    buf = der(h2_min_size=50)
    fill(buf, 20)
    b = buf.sample(6)
    ids = b.rewards.astype(int)
    td = np.array([0.5, -1.5, 2.0, 0.0, 3.0, -0.25])[: len(ids)]
    buf.update_priorities(b.indices, td)
    distinct = {}
    for i, d in zip(ids, td):  # last row of a duplicated transition wins
        distinct[int(i)] = abs(d)
    assert buf.h2_size == len(distinct) and buf.h1_size == 20 - len(distinct)
    assert h1_ids(buf) == set(range(20)) - set(distinct)
    assert h2_logw_by_id(buf) == pytest.approx(distinct)
    np.testing.assert_allclose(buf.h2_weights(), np.exp(list(h2_logw_by_id(buf).values())))
    # moved transitions keep all their fields
    k = buf.h2_size
    np.testing.assert_array_equal(buf.h2.obs[:k, 0], buf.h2.rewards[:k])
    np.testing.assert_array_equal(buf.h2.next_obs[:k, 0], buf.h2.rewards[:k] + 0.5)
    np.testing.assert_array_equal(buf.h2.terminated[:k], buf.h2.rewards[:k].astype(int) % 7 == 0)
    np.testing.assert_array_equal(buf.h2.truncated[:k], buf.h2.rewards[:k].astype(int) % 5 == 0)
    # the moved ones are never sampled from H1 again
    for _ in range(200):
        b = buf.sample(4)
        assert not set(b.rewards[b.source == 0].astype(int).tolist()) & set(distinct)
    # the same handles again are stale: nothing is promoted twice
    buf.update_priorities(b.indices[:0], td[:0])


def test_promotion_copy_keeps_h1():
    buf = der(promote_mode="copy", h2_min_size=50)
    fill(buf, 20)
    b = buf.sample(8)
    buf.update_priorities(b.indices, np.full(8, 1.0))
    assert buf.h1_size == 20 and h1_ids(buf) == set(range(20))
    assert set(h2_ids(buf)) == set(b.rewards.astype(int).tolist())


def test_stale_handles_are_ignored():
    buf = der(capacity=10, h2_min_size=50)
    fill(buf, 10)
    b = buf.sample(5)
    fill(buf, 10, start=10)  # every H1 slot overwritten since the batch was drawn
    buf.update_priorities(b.indices, np.ones(5))
    assert buf.h2_size == 0 and buf.h1_size == 10
    b = buf.sample(5)
    buf.update_priorities(b.indices, np.ones(5))
    n = buf.h2_size
    buf.update_priorities(b.indices, np.ones(5))  # moved already: handles are stale now
    assert buf.h2_size == n


@pytest.mark.parametrize("p", [0.0, 0.3])
def test_promotion_probability(p):
    buf = der(capacity=5000, h2_capacity=5000, p_promote=p, promote_mode="copy", h2_min_size=5000, seed=7)
    fill(buf, 5000)
    tried = 0
    for _ in range(40):
        b = buf.sample(64)
        tried += np.unique(b.indices).size
        buf.update_priorities(b.indices, np.ones(64))
    assert stats.binomtest(buf.h2_size, tried, p).pvalue > P_MIN if p > 0 else buf.h2_size == 0


# ---------------------------------------------------------------- eq. 3
def test_eq3_hand_computed():
    # H2 = {id 0: p = e^1, id 1: p = e^2}; a batch with both, deltas 1 and 3:
    # w = 1/10 and 9/10  ->  log p = 0.1 and 1.8  (p <- p^w)
    buf = der(lam=1.0, h2_min_size=2)
    fill(buf, 2)
    promote(buf, {0: 1.0, 1: -2.0}, batch=2)
    assert h2_logw_by_id(buf) == pytest.approx({0: 1.0, 1: 2.0})
    for _ in range(100):
        b = buf.sample(2)
        if sorted(b.rewards.astype(int).tolist()) == [0, 1]:
            break
    assert (b.source == 1).all()
    buf.update_priorities(b.indices, np.where(b.rewards == 0, 1.0, -3.0))
    got = h2_logw_by_id(buf)
    assert got == pytest.approx({0: 0.1, 1: 1.8})
    np.testing.assert_allclose(sorted(buf.h2_weights()), [math.exp(0.1), math.exp(1.8)])
    st = buf.stats()
    assert st["replay/h2_weight_mean"] == pytest.approx((math.exp(0.1) + math.exp(1.8)) / 2)
    assert st["replay/h2_weight_max"] == pytest.approx(math.exp(1.8))


def test_eq3_duplicates_count_once_and_sum_options():
    # H2 rows id0, id0, id1 with deltas 2, 2, 1 -> the distinct sum is 4 + 1 = 5 ('h2');
    # with eq3_sum='batch' an extra H1 row with delta 3 adds 9, the duplicate row adds 4.
    for mode, total in (("h2", 5.0), ("batch", 4.0 + 4.0 + 1.0 + 9.0)):
        buf = der(lam=1.0, h2_min_size=2, promote_mode="copy", eq3_sum=mode)
        fill(buf, 2)
        promote(buf, {0: 4.0, 1: 4.0}, batch=2)
        for _ in range(1000):
            b = buf.sample(3)
            if sorted(b.rewards.astype(int).tolist()) == [0, 0, 1]:
                break
        assert sorted(b.rewards.astype(int).tolist()) == [0, 0, 1] and (b.source == 1).all()
        idx, td = b.indices, np.where(b.rewards == 0, 2.0, 1.0)
        if mode == "batch":
            buf.lam = 0.0  # test only: draw one H1 row, and keep it from being promoted
            h1 = buf.sample(1)
            assert (h1.source == 0).all()
            idx, td = np.r_[idx, h1.indices], np.r_[td, 3.0]
        buf.update_priorities(idx, td)
        got = h2_logw_by_id(buf)
        assert got[0] == pytest.approx(4.0 * 4.0 / total)
        assert got[1] == pytest.approx(4.0 * 1.0 / total)


def test_weights_fall_towards_one_and_zero_deltas_leave_them():
    buf = der(lam=1.0, h2_min_size=10, promote_mode="copy", seed=3)
    fill(buf, 100)
    promote(buf, {i: 5.0 + i % 4 for i in range(10)}, batch=16)
    rng = np.random.default_rng(0)
    prev = buf.h2_logw[: buf.h2_size].copy()
    for _ in range(200):
        b = buf.sample(8)
        buf.update_priorities(b.indices, rng.standard_normal(8))
        cur = buf.h2_logw[: buf.h2_size]
        assert np.all(cur <= prev + 1e-12) and np.all(cur >= 0)
        prev = cur.copy()
    assert buf.h2_weights().max() < 1.5  # converged towards the baseline 1
    b = buf.sample(8)
    buf.update_priorities(b.indices, np.zeros(8))  # w = 0/0: unchanged
    np.testing.assert_array_equal(buf.h2_logw[: buf.h2_size], prev)


# ---------------------------------------------------------------- H2 sampling
def test_h2_sampling_frequencies_follow_weights():
    buf = der(lam=1.0, h2_min_size=12, promote_mode="copy", seed=5)
    fill(buf, 12)
    deltas = {i: 0.25 * i for i in range(12)}
    promote(buf, deltas, batch=12)
    p = np.exp([0.25 * i for i in range(12)])
    ids = np.concatenate([buf.sample(12).rewards[:] for _ in range(3000)]).astype(int)
    counts = np.bincount(ids, minlength=12)
    expected = p / p.sum() * counts.sum()
    assert stats.chisquare(counts, expected).pvalue > P_MIN


def test_h1_sampling_uniform_over_live_after_moves():
    buf = der(capacity=60, h2_capacity=60, h2_min_size=60, seed=8)
    fill(buf, 60)
    promote(buf, {i: 1.0 for i in range(0, 60, 3)}, batch=16)  # 20 moved out, 40 live
    live = sorted(h1_ids(buf))
    assert len(live) == 40 and not set(range(0, 60, 3)) & set(live)
    ids = np.concatenate([buf.sample(40).rewards for _ in range(2000)]).astype(int)
    counts = np.bincount(ids, minlength=60)
    assert counts[list(range(0, 60, 3))].sum() == 0
    assert stats.chisquare(counts[live]).pvalue > P_MIN


# ---------------------------------------------------------------- ring / eviction
def test_h1_ring_with_holes():
    buf = der(capacity=5, h2_min_size=50)
    fill(buf, 5)
    promote(buf, {1: 1.0, 3: 1.0}, batch=2)
    assert h1_ids(buf) == {0, 2, 4}
    fill(buf, 1, start=5)  # the ring slot of id 0 (written 5 additions ago) is reused
    assert h1_ids(buf) == {2, 4, 5} and buf.h1_size == 3
    fill(buf, 1, start=6)  # the hole left by id 1
    assert h1_ids(buf) == {2, 4, 5, 6} and buf.h1_size == 4
    fill(buf, 9, start=7)  # more than the capacity at once: the newest 5
    assert h1_ids(buf) == {11, 12, 13, 14, 15} and buf.h1_size == 5


def test_h1_dense_index_invariants_under_random_moves():
    rng = np.random.default_rng(9)
    buf = der(capacity=37, h2_capacity=500, h2_min_size=500, seed=9)
    nxt = 0
    for _ in range(300):
        k = int(rng.integers(1, 6))
        fill(buf, k, start=nxt)
        nxt += k
        b = buf.sample(min(8, len(buf)))
        buf.update_priorities(b.indices, rng.random(len(b.indices)))
        n = buf.h1_size
        live = buf.h1_live[:n]
        assert len(set(live.tolist())) == n
        np.testing.assert_array_equal(buf.h1_pos[live], np.arange(n))
        assert (buf.h1_pos >= 0).sum() == n
    assert buf.promoted > 0


def test_h2_fifo_wrap_around():
    buf = der(h2_capacity=4, h2_min_size=4)
    fill(buf, 10)
    for i in range(6):
        promote(buf, {i: 1.0 + i}, batch=2)
    assert sorted(h2_ids(buf)) == [2, 3, 4, 5] and buf.h2_size == 4
    assert h2_logw_by_id(buf) == pytest.approx({2: 3.0, 3: 4.0, 4: 5.0, 5: 6.0})
    assert buf.h2_tree.total == pytest.approx(sum(math.exp(v) for v in (3, 4, 5, 6)))


def test_h2_min_weight_eviction():
    buf = der(h2_capacity=4, h2_min_size=4, h2_eviction="min_weight")
    fill(buf, 10)
    promote(buf, {0: 5.0, 1: 0.5, 2: 7.0, 3: 0.1}, batch=4)
    promote(buf, {4: 2.0}, batch=2)  # evicts id 3 (smallest weight), not id 0 (oldest)
    assert sorted(h2_ids(buf)) == [0, 1, 2, 4]
    promote(buf, {5: 2.0}, batch=2)
    assert sorted(h2_ids(buf)) == [0, 2, 4, 5]


# ---------------------------------------------------------------- numerics
def test_huge_td_errors_stay_finite():
    buf = der(lam=0.5, h2_min_size=4, max_log_weight=50.0)
    fill(buf, 40)
    promote(buf, {0: 1e6, 1: 1e300, 2: 1.0, 3: 700.0}, batch=8)
    lw = h2_logw_by_id(buf)
    assert lw[0] == lw[1] == lw[3] == 50.0 and lw[2] == 1.0
    assert np.all(np.isfinite(buf.h2_weights())) and np.isfinite(buf.h2_tree.total)
    for _ in range(20):
        b = buf.sample(8)
        buf.update_priorities(b.indices, np.full(8, 1e300) * np.where(np.arange(8) % 2, 1, 1e-300))
        assert np.all(np.isfinite(buf.h2_logw)) and np.isfinite(buf.h2_tree.total)
        assert all(math.isfinite(v) for v in buf.stats().values())


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_td_errors_are_rejected_without_change(bad):
    buf = der(h2_min_size=2)
    fill(buf, 20)
    promote(buf, {0: 1.0, 1: 2.0}, batch=4)
    state = buf.state_dict()
    b = buf.sample(4)
    td = np.ones(4)
    td[2] = bad
    with pytest.raises(ValueError, match="non-finite"):
        buf.update_priorities(b.indices, td)
    for key in ("h2/logw", "h1/live", "counters", "h2/tree_leaves"):
        np.testing.assert_array_equal(buf.state_dict()[key], state[key])


def test_max_log_weight_limit_depends_on_h2_capacity():
    with pytest.raises(Exception, match="max_log_weight = 699"):
        der(h2_capacity=100_000, max_log_weight=699.0)
    with pytest.raises(Exception, match="h2_capacity = None; DoubleReplay needs it resolved"):
        DoubleReplay(ReplayConfig(kind="der", capacity=10), (2,))  # the batch-size defaults are not resolved
    with pytest.raises(Exception, match="kind = 'per'"):
        DoubleReplay(ReplayConfig(kind="per", capacity=10, h2_capacity=5, h2_min_size=2), (2,))
    cfg = ReplayConfig(kind="der", capacity=1000, max_log_weight=695.0)  # 700 - ln(12800) = 690.5
    with pytest.raises(Exception, match="max_log_weight = 695"):
        make_replay(cfg, (2,), np.float32, 128, 0)
    # the limit is 700 - ln(h2_capacity), computed by hand here: the same value passes a small H2
    for h2, limit in ((1, 700.0), (10, 697.697), (12_800, 690.543), (100_000, 688.487), (10**8, 681.579)):
        ReplayConfig(kind="der", capacity=10**9, h2_capacity=h2, max_log_weight=limit - 0.001).check()
        with pytest.raises(Exception, match=rf"expected <= 700.0 - ln\(h2_capacity\) = {limit:.1f} "):
            ReplayConfig(kind="der", capacity=10**9, h2_capacity=h2, max_log_weight=limit + 0.001).check()
    der(h2_capacity=10, max_log_weight=695.0)  # accepted: 695 < 697.7


def test_lambda_zero_is_uniform_dqn_and_one_is_h2_only():
    b0 = der(lam=0.0, h2_min_size=1)
    fill(b0, 50)
    for _ in range(30):
        b = b0.sample(8)
        assert (b.source == 0).all()
        b0.update_priorities(b.indices, np.ones(8))
    assert b0.h1_size == 50 and b0.h2_size == 0  # nothing promoted: H1 stays a plain DQN buffer
    b1 = der(lam=1.0, h2_min_size=8, promote_mode="copy")
    fill(b1, 50)
    for _ in range(30):
        ready = b1.h2_size >= 8
        b = b1.sample(8)
        assert (b.source == (1 if ready else 0)).all()
        b1.update_priorities(b.indices, np.ones(8))
    assert b1.h2_size >= 8


@pytest.mark.slow
def test_building_a_prioritized_buffer_loads_the_compiled_kernels() -> None:
    """make_replay loads the numba kernels (warm_up_kernels), so the ~0.5 s load does not fall on
    the first gradient step. Run in a fresh process: this one may have loaded them already."""
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from der_ros.replay import double_replay_kernels as d, sum_tree_kernels as s\n"
        "from der_ros.replay._numba import HAVE_NUMBA\n"
        "from der_ros.replay.config import ReplayConfig\n"
        "from der_ros.replay.factory import make_replay\n"
        "assert HAVE_NUMBA\n"
        "kernels = (d._der_plan_nb, d._dense_remove_nb, s._sample_nb, s._propagate_nb)\n"
        "assert not any(k.signatures for k in kernels)\n"
        "make_replay(ReplayConfig(kind='der', capacity=1000, h2_capacity=256), (3,), np.float32, 32)\n"
        "print([len(k.signatures) for k in kernels])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert all(int(n) >= 1 for n in out.stdout.strip().strip("[]").split(","))
