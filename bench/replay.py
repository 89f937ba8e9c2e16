"""Replay benchmark: der_ros buffers against cpprb and TorchRL, same data, same process.

Measures steps per second of the work the learner does on every gradient step:

* ``uniform_sample``: sample 128 from a uniform buffer of 50,000;
* ``per_step``: PER sample 128 + update priorities (capacity 50,000, alpha 0.6, beta 0.4);
* ``der_step``: DER with lambda = 0.5, H1 = 50,000, H2 = 12,800 (= 100 x 128): sample 128
  (64 from H1, 64 from H2), then eq. 3 on the H2 rows and promotion of the H1 rows.
  Peers have no DER, so it is built from their uniform + prioritized buffers: sample 64 from
  a uniform buffer and 64 from a prioritized one standing in for H2, apply eq. 3 to the H2
  rows (log-weights kept in a numpy side array, priorities = exp(log w), alpha = 1) and
  add the 64 H1 rows to the prioritized buffer at priority e^|delta|. Peers cannot remove
  from their uniform buffer, so ours runs with ``promote_mode='copy'`` (the same work).

Observations are float32 vectors of size 4. Each number is the median over repeats of a
timed loop after a warm-up. Prints a table, then one JSON line.

    .venv/bin/python bench/replay.py            # ~1 minute
    .venv/bin/python bench/replay.py --quick    # a few seconds
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings
from collections.abc import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # TorchRL logs storage set-up to stdout otherwise

import numpy as np  # noqa: E402

from der_ros.replay.config import ReplayConfig  # noqa: E402
from der_ros.replay.double_replay import DoubleReplay  # noqa: E402
from der_ros.replay.prioritized import PrioritizedReplay  # noqa: E402
from der_ros.replay.uniform import UniformReplay  # noqa: E402

N1 = 50_000
B = 128
LAM = 0.5
N2 = 100 * B
OBS = 4


def measure(step: Callable[[], object], seconds: float, repeats: int, warmup: bool = True) -> float:
    """Median calls/s over ``repeats`` loops of ``seconds / repeats`` each (after a warm-up)."""
    t_end = time.perf_counter() + min(0.3, seconds / 4)
    while warmup and time.perf_counter() < t_end:
        step()
    rates = []
    for _ in range(repeats):
        n = 0
        t0 = time.perf_counter()
        t_end = t0 + seconds / repeats
        while True:
            for _ in range(20):
                step()
            n += 20
            t = time.perf_counter()
            if t >= t_end:
                break
        rates.append(n / (t - t0))
    return statistics.median(rates)


def make_data(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "obs": rng.standard_normal((n, OBS)).astype(np.float32),
        "act": rng.integers(0, 3, n).astype(np.int64),
        "rew": rng.standard_normal(n).astype(np.float32),
        "next_obs": rng.standard_normal((n, OBS)).astype(np.float32),
        "terminated": rng.random(n) < 0.01,
        "truncated": rng.random(n) < 0.01,
    }


def td_source(seed: int = 1, n: int = 1 << 16) -> Callable[[int], np.ndarray]:
    """Precomputed TD errors, so generating them is not part of what is timed."""
    pool = np.random.default_rng(seed).standard_normal(n).astype(np.float32)
    state = {"i": 0}

    def take(k: int) -> np.ndarray:
        i = state["i"]
        if i + k > n:
            i = 0
        state["i"] = i + k
        return pool[i : i + k]

    return take


def _fill(buf, data) -> None:
    buf.add_batch(data["obs"], data["act"], data["rew"], data["next_obs"], data["terminated"], data["truncated"])


# ---------------------------------------------------------------- ours
def ours_uniform(data):
    buf = UniformReplay(N1, (OBS,), np.float32, seed=0)
    _fill(buf, data)
    return lambda: buf.sample(B)


def ours_per(data):
    buf = PrioritizedReplay(N1, (OBS,), np.float32, alpha=0.6, beta0=0.4, seed=0)
    _fill(buf, data)
    td = td_source()

    def step():
        b = buf.sample(B)
        buf.update_priorities(b.indices, td(B))

    return step


def ours_der(data, promote_mode: str = "copy"):
    cfg = ReplayConfig(kind="der", capacity=N1, h2_capacity=N2, lam=LAM, h2_min_size=B, promote_mode=promote_mode)
    buf = DoubleReplay(cfg, (OBS,), np.float32, seed=0)
    _fill(buf, data)
    td = td_source()
    n1 = B - int(np.floor(LAM * B + 0.5))
    fresh = make_data(n1 * 64, seed=5)
    state = {"i": 0}

    def step():
        b = buf.sample(B)
        buf.update_priorities(b.indices, td(B))
        if promote_mode == "move":  # keep H1 full: as many new transitions as were moved out
            i = state["i"]
            state["i"] = (i + n1) % (n1 * 64)
            buf.add_batch(*(fresh[k][i : i + n1] for k in ("obs", "act", "rew", "next_obs", "terminated", "truncated")))

    while buf.h2_size < N2:  # fill H2 through promotions
        step()
    return step


# ---------------------------------------------------------------- cpprb
def _cpprb_env():
    return {
        "obs": {"shape": OBS, "dtype": np.float32},
        "act": {"dtype": np.int64},
        "rew": {"dtype": np.float32},
        "next_obs": {"shape": OBS, "dtype": np.float32},
        "terminated": {"dtype": np.bool_},
        "truncated": {"dtype": np.bool_},
    }


def _cpprb_add(rb, data, **kw):
    return rb.add(
        obs=data["obs"], act=data["act"], rew=data["rew"], next_obs=data["next_obs"],
        terminated=data["terminated"], truncated=data["truncated"], **kw,
    )  # fmt: skip


def cpprb_uniform(data):
    import cpprb

    rb = cpprb.ReplayBuffer(N1, _cpprb_env())
    _cpprb_add(rb, data)
    return lambda: rb.sample(B)


def cpprb_per(data):
    import cpprb

    rb = cpprb.PrioritizedReplayBuffer(N1, _cpprb_env(), alpha=0.6, eps=1e-6)
    _cpprb_add(rb, data)
    td = td_source()

    def step():
        s = rb.sample(B, beta=0.4)
        rb.update_priorities(s["indexes"], np.abs(td(B)))

    return step


def cpprb_der(data):
    import cpprb

    n2 = int(np.floor(LAM * B + 0.5))
    n1 = B - n2
    h1 = cpprb.ReplayBuffer(N1, _cpprb_env())
    _cpprb_add(h1, data)
    h2 = cpprb.PrioritizedReplayBuffer(N2, _cpprb_env(), alpha=1.0, eps=0.0)
    logw = np.zeros(N2, dtype=np.float64)
    td = td_source()

    def step():
        s1 = h1.sample(n1)
        d = np.abs(td(B).astype(np.float64))
        d1, d2 = d[:n1], d[n1:]
        if h2.get_stored_size() >= B:
            s2 = h2.sample(n2, beta=0.0)
            idx2 = s2["indexes"].astype(np.int64)
            w = d2 * d2 / np.dot(d2, d2)  # eq. 3
            logw[idx2] *= w
            h2.update_priorities(idx2, np.exp(logw[idx2]))
        lw = np.minimum(d1, 50.0)
        first = _cpprb_add(h2, s1, priorities=np.exp(lw))  # promotion
        logw[(first + np.arange(n1)) % N2] = lw

    while h2.get_stored_size() < N2:
        step()
    return step


# ---------------------------------------------------------------- TorchRL
def _td(data, n=None):
    import torch
    from tensordict import TensorDict

    sl = slice(None) if n is None else slice(0, n)
    return TensorDict(
        {k: torch.from_numpy(np.ascontiguousarray(v[sl])) for k, v in data.items()},
        batch_size=[len(data["act"][sl])],
    )


def torchrl_uniform(data):
    from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(N1), sampler=RandomSampler(), batch_size=B)
    rb.extend(_td(data))
    return lambda: rb.sample()


def torchrl_per(data):
    import torch
    from torchrl.data import LazyTensorStorage, TensorDictPrioritizedReplayBuffer

    rb = TensorDictPrioritizedReplayBuffer(alpha=0.6, beta=0.4, eps=1e-6, storage=LazyTensorStorage(N1), batch_size=B)
    rb.extend(_td(data))
    td = td_source()

    def step():
        s = rb.sample()
        rb.update_priority(s["index"], torch.from_numpy(np.abs(td(B))))

    return step


def torchrl_der(data):
    import torch
    from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictPrioritizedReplayBuffer, TensorDictReplayBuffer

    n2 = int(np.floor(LAM * B + 0.5))
    n1 = B - n2
    h1 = TensorDictReplayBuffer(storage=LazyTensorStorage(N1), sampler=RandomSampler(), batch_size=n1)
    h1.extend(_td(data))
    h2 = TensorDictPrioritizedReplayBuffer(alpha=1.0, beta=0.0, eps=0.0, storage=LazyTensorStorage(N2), batch_size=n2)
    logw = np.zeros(N2, dtype=np.float64)
    td = td_source()

    def step():
        s1 = h1.sample()
        d = np.abs(td(B).astype(np.float64))
        d1, d2 = d[:n1], d[n1:]
        if len(h2) >= B:
            s2 = h2.sample()
            idx2 = s2["index"].numpy().astype(np.int64)
            w = d2 * d2 / np.dot(d2, d2)
            logw[idx2] *= w
            h2.update_priority(torch.from_numpy(idx2), torch.from_numpy(np.exp(logw[idx2]).astype(np.float32)))
        lw = np.minimum(d1, 50.0)
        s1 = s1.exclude("index")
        idx = h2.extend(s1, update_priority=False)  # promotion: priority e^|delta| set explicitly
        idx = np.asarray(idx, dtype=np.int64)
        h2.update_priority(torch.from_numpy(idx), torch.from_numpy(np.exp(lw).astype(np.float32)))
        logw[idx] = lw

    while len(h2) < N2:
        step()
    return step


# ---------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short loops (a few seconds in total)")
    ap.add_argument("--seconds", type=float, default=None, help="timed seconds per measurement (default 3, quick 0.3)")
    ap.add_argument("--repeats", type=int, default=None, help="repeats per measurement (default 5, quick 3)")
    args = ap.parse_args(argv)
    seconds = args.seconds if args.seconds is not None else (0.3 if args.quick else 3.0)
    repeats = args.repeats if args.repeats is not None else (3 if args.quick else 5)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    warnings.filterwarnings("ignore")

    data = make_data(N1)
    cases = [
        ("uniform_sample_per_s", "ours", "uniform sample 128", ours_uniform),
        ("cpprb_uniform_sample_per_s", "cpprb", "uniform sample 128", cpprb_uniform),
        ("torchrl_uniform_sample_per_s", "torchrl", "uniform sample 128", torchrl_uniform),
        ("per_step_per_s", "ours", "PER sample 128 + update", ours_per),
        ("cpprb_per_step_per_s", "cpprb", "PER sample 128 + update", cpprb_per),
        ("torchrl_per_step_per_s", "torchrl", "PER sample 128 + update", torchrl_per),
        ("der_step_per_s", "ours", "DER step (copy)", ours_der),
        ("der_move_step_per_s", "ours", "DER step (move + refill H1)", lambda d: ours_der(d, "move")),
        ("cpprb_der_step_per_s", "cpprb", "DER step (emulated)", cpprb_der),
        ("torchrl_der_step_per_s", "torchrl", "DER step (emulated)", torchrl_der),
    ]
    result: dict[str, object] = {"batch": B, "n1": N1, "n2": N2, "lam": LAM, "seconds": seconds, "repeats": repeats}
    errors: dict[str, str] = {}
    steps: dict[str, Callable[[], object]] = {}
    for key, _who, _what, build in cases:
        try:
            step = build(data)
            warm_end = time.perf_counter() + min(0.3, seconds / 4)
            while time.perf_counter() < warm_end:
                step()
            steps[key] = step
        except Exception as exc:  # a peer that cannot run here is reported, not fatal
            errors[key] = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
    # Repeats are interleaved across implementations, so a load change on the machine hits
    # ours and the peers alike and the ratios stay meaningful.
    rates: dict[str, list[float]] = {k: [] for k in steps}
    for _ in range(repeats):
        for key, step in steps.items():
            rates[key].append(measure(step, seconds / repeats, 1, warmup=False))
    rows = []
    for key, who, what, _build in cases:
        rate = statistics.median(rates[key]) if key in rates else None
        result[key] = None if rate is None else round(rate, 1)
        rows.append((what, who, rate))

    def ratio(a: str, b: str) -> float | None:
        x, y = result.get(a), result.get(b)
        return round(x / y, 2) if isinstance(x, float) and isinstance(y, float) and y > 0 else None

    result["der_vs_cpprb"] = ratio("der_step_per_s", "cpprb_der_step_per_s")
    result["der_vs_torchrl"] = ratio("der_step_per_s", "torchrl_der_step_per_s")
    result["per_vs_cpprb"] = ratio("per_step_per_s", "cpprb_per_step_per_s")
    result["per_vs_torchrl"] = ratio("per_step_per_s", "torchrl_per_step_per_s")
    result["uniform_vs_cpprb"] = ratio("uniform_sample_per_s", "cpprb_uniform_sample_per_s")
    result["targets_met"] = {
        "der_ge_2x_cpprb": (result["der_vs_cpprb"] or 0) >= 2.0,
        "per_ge_cpprb": (result["per_vs_cpprb"] or 0) >= 1.0,
    }
    if errors:
        result["errors"] = errors

    print(f"{'benchmark':32s} {'impl':8s} {'calls/s':>12s} {'us/call':>9s}")
    for what, who, rate in rows:
        if rate is None:
            print(f"{what:32s} {who:8s} {'n/a':>12s} {'':>9s}  ({errors.get(_key(cases, what, who), '')[:60]})")
        else:
            print(f"{what:32s} {who:8s} {rate:12,.0f} {1e6 / rate:9.1f}")
    print(json.dumps(result))
    sys.stdout.flush()
    return 0


def _key(cases, what: str, who: str) -> str:
    for key, w, t, _ in cases:
        if w == who and t == what:
            return key
    return ""


if __name__ == "__main__":
    sys.exit(main())
