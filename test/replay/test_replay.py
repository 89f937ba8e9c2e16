"""Replay core: storage, sum tree, uniform and prioritized sampling, config errors, save/load.

Statistical tests use fixed seeds and a chi-square goodness-of-fit test at significance
1e-3 (the tests are deterministic; the level states how surprising a failure would be).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from scipy import stats

from der_ros.configuration import ConfigError, from_dict
from der_ros.replay.base import Batch
from der_ros.replay.config import ReplayConfig
from der_ros.replay.double_replay import DoubleReplay
from der_ros.replay.factory import load_replay, make_replay
from der_ros.replay.prioritized import PrioritizedReplay
from der_ros.replay.storage import ReplayMemoryError, storage_bytes
from der_ros.replay.sum_tree import SumTree
from der_ros.replay.uniform import UniformReplay

P_MIN = 1e-3  # chi-square significance level used throughout


def fill(buf, n: int, start: int = 0, obs_shape=(2,), dtype=np.float32) -> None:
    """Add n transitions whose reward (and obs[..., 0]) is their running id."""
    ids = np.arange(start, start + n)
    obs = np.zeros((n, *obs_shape), dtype=dtype)
    obs.reshape(n, -1)[:, 0] = ids
    buf.add_batch(obs, ids % 3, ids.astype(np.float32), obs, ids % 7 == 0, ids % 5 == 0)


def chi2_p(counts: np.ndarray, probs: np.ndarray) -> float:
    expected = probs / probs.sum() * counts.sum()
    return float(stats.chisquare(counts, expected).pvalue)


# ---------------------------------------------------------------- sum tree
class TestSumTree:
    @pytest.mark.parametrize("n", [1, 2, 7, 1000, 5000])
    def test_find_matches_prefix_sums(self, n):
        rng = np.random.default_rng(n)
        tree = SumTree(n, root_width=64)
        v = rng.random(n) + 1e-3
        tree.set(np.arange(n), v)
        assert tree.total == pytest.approx(v.sum(), rel=1e-12)
        cs = np.cumsum(v)
        u = np.sort(rng.random(2000)) * cs[-1] * (1 - 1e-12)
        np.testing.assert_array_equal(tree.find(u), np.searchsorted(cs, u, side="right"))

    def test_edges_never_return_zero_leaf_or_past_limit(self):
        tree = SumTree(16, root_width=4)
        v = np.zeros(16)
        v[[0, 3, 4, 9]] = [1.0, 2.0, 1e-9, 3.0]
        tree.set(np.arange(16), v)
        total = tree.total
        u = np.array([0.0, 1.0, 3.0, 3.0 + 1e-9, np.nextafter(total, 0.0), total, total * 2])
        got = tree.find(u)
        assert set(got.tolist()) <= {0, 3, 4, 9}
        assert got[-1] == 9 and got[-2] == 9 and got[-3] == 9
        # limit: nothing at or beyond it is ever returned, even for u past the total
        tree2 = SumTree(8)
        tree2.set(np.arange(3), [1.0, 1.0, 1.0])
        rng = np.random.default_rng(0)
        for _ in range(200):
            assert tree2.sample(rng, 5, limit=3).max() < 3
        assert tree2.find(np.array([5.0]), limit=3)[0] == 2

    def test_incremental_updates_equal_rebuild_bitwise(self):
        rng = np.random.default_rng(1)
        tree = SumTree(3000, root_width=32)
        for _ in range(50):
            idx = rng.integers(0, 3000, 64)
            tree.set(idx, rng.random(64) * 10 ** rng.uniform(-5, 5))
        levels = [lvl.copy() for lvl in tree.levels]
        tree.rebuild()
        for a, b in zip(levels, tree.levels):
            np.testing.assert_array_equal(a, b)

    def test_rejects_bad_values(self):
        tree = SumTree(4)
        with pytest.raises(ValueError):
            tree.set([0], [np.nan])
        with pytest.raises(ValueError):
            tree.set([0], [-1.0])
        with pytest.raises(IndexError):
            tree.set([4], [1.0])

    def test_sampling_frequencies(self):
        rng = np.random.default_rng(2)
        n = 40
        tree = SumTree(n, root_width=8)
        p = rng.random(n) ** 3 + 0.01
        tree.set(np.arange(n), p)
        counts = np.bincount(np.concatenate([tree.sample(rng, 32) for _ in range(3000)]), minlength=n)
        assert chi2_p(counts, p) > P_MIN


# ---------------------------------------------------------------- storage + uniform
class TestUniform:
    def test_frequencies_uniform(self):
        buf = UniformReplay(50, (2,), seed=3)
        fill(buf, 50)
        ids = np.concatenate([buf.sample(50).rewards for _ in range(2500)]).astype(int)
        counts = np.bincount(ids, minlength=50)
        assert chi2_p(counts, np.ones(50)) > P_MIN

    def test_batch_fields_and_dtypes(self):
        buf = UniformReplay(10, (2,), seed=0)
        fill(buf, 10)
        b = buf.sample(8)
        assert isinstance(b, Batch)
        assert b.obs.dtype == np.float32 and b.obs.shape == (8, 2)
        assert b.actions.dtype == np.int64 and b.rewards.dtype == np.float32
        assert b.terminated.dtype == np.bool_ and b.truncated.dtype == np.bool_
        assert b.indices.dtype == np.int64 and b.weights.dtype == np.float32 and b.source.dtype == np.uint8
        np.testing.assert_array_equal(b.weights, 1.0)
        np.testing.assert_array_equal(b.source, 0)
        ids = b.rewards.astype(int)
        np.testing.assert_array_equal(b.obs[:, 0], ids)
        np.testing.assert_array_equal(b.actions, ids % 3)
        np.testing.assert_array_equal(b.terminated, ids % 7 == 0)  # kept apart from truncated
        np.testing.assert_array_equal(b.truncated, ids % 5 == 0)
        buf.update_priorities(b.indices, np.ones(8))  # no-op, same interface

    def test_wrap_around_keeps_newest(self):
        buf = UniformReplay(5, (2,), seed=0)
        for i in range(12):
            buf.add(np.array([i, 0], np.float32), i % 3, float(i), np.zeros(2, np.float32), False, i == 11)
        assert len(buf) == 5
        assert set(buf.storage.rewards.tolist()) == {7.0, 8.0, 9.0, 10.0, 11.0}
        buf2 = UniformReplay(5, (2,), seed=0)
        fill(buf2, 3)
        fill(buf2, 9, start=3)  # batch larger than the capacity
        assert sorted(buf2.storage.rewards.tolist()) == [7.0, 8.0, 9.0, 10.0, 11.0]
        assert buf2.storage.cursor == 12 % 5

    def test_uint8_observations_stay_uint8(self):
        buf = make_replay(ReplayConfig(kind="der", capacity=20, h2_capacity=10), (8, 8, 4), np.uint8, 4, 0)
        frames = np.full((6, 8, 8, 4), 255, dtype=np.uint8)
        buf.add_batch(frames, np.zeros(6), np.zeros(6), frames, np.zeros(6, bool), np.zeros(6, bool))
        b = buf.sample(4)
        assert b.obs.dtype == np.uint8 and b.next_obs.dtype == np.uint8
        assert buf.h1.obs.dtype == np.uint8 and buf.h2.obs.dtype == np.uint8
        assert int(b.obs.max()) == 255
        with pytest.raises(ValueError, match="uint8"):
            buf.add(np.zeros((8, 8, 4), np.float32), 0, 0.0, np.zeros((8, 8, 4), np.float32), False, False)
        with pytest.raises(ValueError, match="shape"):
            buf.add(np.zeros((8, 8), np.uint8), 0, 0.0, np.zeros((8, 8), np.uint8), False, False)

    def test_memory_estimate_and_error(self):
        assert storage_bytes(1000, (84, 84, 4), np.uint8) == 1000 * (2 * 84 * 84 * 4 + 14 + 40)
        assert storage_bytes(10, (4,), np.float32) == 10 * (2 * 16 + 14 + 40)
        cfg = ReplayConfig(kind="uniform", capacity=1_000_000)
        with pytest.raises(ReplayMemoryError) as exc:
            make_replay(cfg, (84, 84, 4), np.uint8, 32, 0, available_bytes=10 * 2**30)
        msg = str(exc.value)
        for part in ("capacity=1000000", "(84, 84, 4)", "uint8", f"{storage_bytes(1_000_000, (84, 84, 4), np.uint8):,}",
                     f"{10 * 2**30:,}"):
            assert part in msg
        assert isinstance(exc.value, ConfigError)
        with pytest.raises(ReplayMemoryError, match="h2_capacity"):
            make_replay(ReplayConfig(kind="der", capacity=1000), (84, 84, 4), np.uint8, 32, 0, available_bytes=10**6)
        # the real check against this machine's memory: a petabyte never fits
        with pytest.raises(ReplayMemoryError):
            UniformReplay(10**12, (84, 84, 4), np.uint8)


# ---------------------------------------------------------------- PER
class TestPrioritized:
    def test_frequencies_follow_priorities(self):
        buf = PrioritizedReplay(30, (2,), alpha=0.7, beta0=0.4, eps=1e-6, seed=4)
        fill(buf, 30)
        delta = np.linspace(0.0, 3.0, 30)
        buf.update_priorities(np.arange(30), delta)
        expected = (np.abs(delta) + 1e-6) ** 0.7
        np.testing.assert_allclose(buf.tree.leaves[:30], expected, rtol=1e-12)
        ids = np.concatenate([buf.sample(30).rewards for _ in range(3000)]).astype(int)
        assert chi2_p(np.bincount(ids, minlength=30), expected) > P_MIN

    def test_importance_weights_and_beta_annealing(self):
        buf = PrioritizedReplay(20, (2,), alpha=0.5, beta0=0.4, beta_steps=10, seed=5)
        fill(buf, 20)
        buf.update_priorities(np.arange(20), np.arange(20) + 1.0)
        betas = []
        for k in range(12):
            beta = buf.beta
            betas.append(beta)
            assert buf.stats()["replay/per_beta"] == pytest.approx(beta)
            b = buf.sample(8)
            p = buf.tree.leaves[b.indices]
            n_p = 20 * p / buf.tree.total
            w = n_p**-beta / (n_p**-beta).max()
            np.testing.assert_allclose(b.weights, w, rtol=1e-6)
            assert b.weights.max() == pytest.approx(1.0)
            assert k < 10 or beta == 1.0
        np.testing.assert_allclose(betas[:11], 0.4 + 0.6 * np.minimum(1, np.arange(11) / 10))

    def test_new_items_enter_at_max_priority(self):
        buf = PrioritizedReplay(8, (2,), alpha=1.0, seed=0)
        fill(buf, 4)
        np.testing.assert_array_equal(buf.tree.leaves[:4], 1.0)  # before any update
        buf.update_priorities(np.array([0, 1]), np.array([5.0, 0.5]))
        fill(buf, 1, start=4)
        assert buf.tree.leaves[4] == pytest.approx(5.0 + 1e-6)

    def test_wrap_around(self):
        buf = PrioritizedReplay(4, (2,), alpha=1.0, seed=0)
        fill(buf, 4)
        buf.update_priorities(np.arange(4), np.array([0.0, 0.0, 9.0, 0.0]))
        fill(buf, 2, start=4)  # overwrites ids 0 and 1 at the max priority 9
        assert len(buf) == 4
        assert sorted(buf.storage.rewards.tolist()) == [2.0, 3.0, 4.0, 5.0]
        np.testing.assert_allclose(buf.tree.leaves[:4], [9 + 1e-6, 9 + 1e-6, 9 + 1e-6, 1e-6])
        rng_ids = np.concatenate([buf.sample(4).rewards for _ in range(300)])
        assert set(rng_ids.tolist()) <= {2.0, 4.0, 5.0, 3.0}

    def test_partially_filled_never_samples_empty_slots(self):
        buf = PrioritizedReplay(1000, (2,), seed=6)
        fill(buf, 3)
        buf.update_priorities(np.arange(3), np.array([1e-9, 0.0, 1e3]))
        for _ in range(300):
            b = buf.sample(3)
            assert b.indices.max() < 3 and b.indices.min() >= 0

    def test_huge_and_nonfinite_td_errors(self):
        buf = PrioritizedReplay(16, (2,), alpha=1.0, seed=0)
        fill(buf, 16)
        buf.update_priorities(np.arange(16), np.full(16, 1e6))
        buf.update_priorities(np.arange(2), np.array([1e300, 1e-300]))
        b = buf.sample(16)
        assert np.all(np.isfinite(b.weights)) and np.isfinite(buf.tree.total)
        before = buf.tree.leaves.copy()
        for bad in (np.nan, np.inf, -np.inf):
            with pytest.raises(ValueError, match="non-finite"):
                buf.update_priorities(np.arange(2), np.array([1.0, bad]))
        np.testing.assert_array_equal(buf.tree.leaves, before)


# ---------------------------------------------------------------- config errors
BAD_FIELDS = [
    ("lam", 1.5),
    ("lam", -0.1),
    ("capacity", 0),
    ("capacity", -5),
    ("h2_capacity", 0),
    ("h2_min_size", 0),
    ("alpha", 1.5),
    ("alpha", -0.1),
    ("beta0", 1.2),
    ("beta0", -0.2),
    ("beta_steps", -1),
    ("per_eps", 0.0),
    ("p_promote", 1.01),
    ("p_promote", -0.5),
    ("max_log_weight", 0.0),
    ("max_log_weight", 1e4),
    ("kind", "fancy"),
    ("promote_mode", "teleport"),
    ("h2_eviction", "random"),
    ("eq3_sum", "all"),
]


@pytest.mark.parametrize("field,value", BAD_FIELDS)
def test_bad_parameter_names_field_and_value(field, value):
    with pytest.raises(ConfigError) as exc:
        from_dict(ReplayConfig, {field: value})
    assert field in str(exc.value) and repr(value) in str(exc.value)
    cfg = ReplayConfig()
    setattr(cfg, field, value)  # the same through make_replay (a config built in code)
    with pytest.raises(ConfigError) as exc:
        make_replay(cfg, (2,), np.float32, 4, 0)
    assert field in str(exc.value) and repr(value) in str(exc.value)


@pytest.mark.parametrize(
    "cfg,batch,needle",
    [
        (ReplayConfig(kind="uniform", capacity=10), 11, "batch_size = 11"),
        (ReplayConfig(kind="per", capacity=10), 0, "batch_size = 0"),
        (ReplayConfig(kind="der", capacity=100, h2_capacity=10), 16, "h2_capacity (10)"),
        (ReplayConfig(kind="der", capacity=100, h2_capacity=10, h2_min_size=11), 4, "h2_min_size = 11"),
        (ReplayConfig(kind="der", capacity=100, h2_min_size=500), 4, "h2_min_size = 500"),
    ],
)
def test_bad_batch_size_or_cross_field(cfg, batch, needle):
    with pytest.raises(ConfigError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        make_replay(cfg, (2,), np.float32, batch, 0)


@pytest.mark.parametrize("kind", ["uniform", "per", "der"])
def test_sample_larger_than_current_size_raises(kind):
    buf = make_replay(ReplayConfig(kind=kind, capacity=100, h2_capacity=50), (2,), np.float32, 8, 0)
    fill(buf, 5)
    with pytest.raises(ConfigError, match="batch_size = 8.*current replay size \\(5\\)"):
        buf.sample(8)
    with pytest.raises(ConfigError, match="capacity"):
        buf.sample(1000)


# ---------------------------------------------------------------- save / load
def buf_shape(buf) -> tuple[int, ...]:
    return (buf.h1 if isinstance(buf, DoubleReplay) else buf.storage).obs_shape


def _run(buf, steps: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    out = []
    for t in range(steps):
        b = buf.sample(8)
        buf.update_priorities(b.indices, rng.standard_normal(8) * 3)
        fill(buf, 2, start=1000 + 2 * t + seed * 10_000, obs_shape=buf_shape(buf))
        out.append((b, buf.stats()))
    return out


@pytest.mark.parametrize("kind", ["uniform", "per", "der"])
def test_save_load_continues_identically(kind, tmp_path):
    cfg = ReplayConfig(kind=kind, capacity=64, h2_capacity=24, h2_min_size=8, lam=0.5, p_promote=0.7, beta_steps=50)
    buf = make_replay(cfg, (3,), np.float32, 8, seed=11)
    fill(buf, 40, obs_shape=(3,))
    _run(buf, 30, seed=1)  # wraps H2 (24) and gets the trees and RNG going
    path = tmp_path / "sub" / "replay.npz"
    buf.save(path)
    assert sorted(os.listdir(path.parent)) == ["replay.npz"]  # no temp file left behind
    twin = load_replay(path)
    assert type(twin) is type(buf) and len(twin) == len(buf)
    a, b = _run(buf, 25, seed=2), _run(twin, 25, seed=2)
    for (ba, sa), (bb, sb) in zip(a, b):
        for fa, fb in zip(ba, bb):
            np.testing.assert_array_equal(fa, fb)
        assert sa == sb
    # state_dict / load_state_dict into a fresh buffer works the same way (the agent checkpoint path)
    fresh = make_replay(cfg, (3,), np.float32, 8, seed=999)
    fresh.load_state_dict(buf.state_dict())
    for fa, fb in zip(fresh.sample(8), buf.sample(8)):
        np.testing.assert_array_equal(fa, fb)
    # overwriting an existing file is atomic too
    buf.save(path)
    assert sorted(os.listdir(path.parent)) == ["replay.npz"]


def test_load_state_dict_rejects_other_buffer(tmp_path):
    a = UniformReplay(10, (2,), seed=0)
    b = UniformReplay(12, (2,), seed=0)
    with pytest.raises(ValueError, match="capacity = 10"):
        b.load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match="kind"):
        PrioritizedReplay(10, (2,)).load_state_dict(a.state_dict())


def test_der_defaults_follow_the_paper():
    buf = make_replay(ReplayConfig(), (4,), np.float32, 128, 0)
    assert isinstance(buf, DoubleReplay)
    assert buf.capacity == 50_000 and buf.h2_capacity == 128 * 100 and buf.h2_min_size == 128
    # 'copy' is the library default (every shipped config uses it); 'move' is the authors' rule
    assert math.isclose(buf.lam, 0.5) and buf.p_promote == 1.0 and buf.promote_mode == "copy"


# ---------------------------------------------------------------- compiled vs numpy kernels
def _set_numba(buf, flag: bool) -> None:
    tree = buf.tree if isinstance(buf, PrioritizedReplay) else buf.h2_tree
    tree.use_numba = flag


@pytest.mark.skipif(not __import__("der_ros.replay._numba", fromlist=["x"]).HAVE_NUMBA,
                    reason="numba not installed: only the numpy kernels exist")
@pytest.mark.parametrize("kind", ["per", "der"])
@pytest.mark.parametrize("eq3_sum", ["h2", "batch"])
def test_numba_and_numpy_kernels_agree_bitwise(kind, eq3_sum):
    """The compiled kernels and their numpy fallbacks give identical batches and states."""
    cfg = ReplayConfig(kind=kind, capacity=300, h2_capacity=40, h2_min_size=8, lam=0.5, p_promote=0.8,
                       eq3_sum=eq3_sum)
    runs = []
    for flag in (True, False):
        buf = make_replay(cfg, (3,), np.float32, 16, seed=4)
        _set_numba(buf, flag)
        fill(buf, 200, obs_shape=(3,))
        rng = np.random.default_rng(0)
        out = []
        for t in range(150):
            b = buf.sample(16)
            buf.update_priorities(b.indices, rng.standard_normal(16) * 10 ** rng.uniform(-3, 3))
            if t % 10 == 0:
                fill(buf, 7, start=10_000 + t, obs_shape=(3,))
            out.append(b)
        runs.append((out, buf.state_dict()))
    (a, sa), (b, sb) = runs
    for ba, bb in zip(a, b):
        for fa, fb in zip(ba, bb):
            np.testing.assert_array_equal(fa, fb)
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=key)


def test_state_dict_copy_flag():
    buf = UniformReplay(10, (2,), seed=0)
    fill(buf, 4)
    copied, viewed = buf.state_dict(), buf.state_dict(copy=False)
    fill(buf, 2, start=4)
    assert copied["size"] == 4 and copied["data/rewards"][4] == 0.0  # unaffected by later adds
    assert viewed["data/rewards"][4] == 4.0  # a view follows the buffer


@pytest.mark.parametrize("kind", ["uniform", "per", "der"])
def test_add_one_by_one_equals_add_batch(kind):
    """The per-step add() fast path leaves exactly the state add_batch() leaves."""
    cfg = ReplayConfig(kind=kind, capacity=7, h2_capacity=8, h2_min_size=2)
    one, many = (make_replay(cfg, (2,), np.float32, 2, seed=1) for _ in range(2))
    ids = np.arange(11)
    obs = np.stack([ids, -ids], axis=1).astype(np.float64)  # float64 in, float32 stored
    for i in ids:
        one.add(obs[i], int(i % 3), float(i), obs[i] + 1, bool(i % 4 == 0), bool(i % 5 == 0))
    many.add_batch(obs, ids % 3, ids.astype(float), obs + 1, ids % 4 == 0, ids % 5 == 0)
    sa, sb = one.state_dict(), many.state_dict()
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=key)
    with pytest.raises(ValueError, match="reward"):
        one.add(obs[0], 0, float("nan"), obs[0], False, False)
    with pytest.raises(ValueError, match="shape"):
        one.add(np.zeros(3), 0, 0.0, np.zeros(3), False, False)
