"""DoubleReplay: double experience replay (DER), paper section 3, Algorithm 1, eq. 3.

Two memories:

* **H1** (capacity N1, paper 50,000) receives every new transition and is sampled
  uniformly: "In H_1, we use uniform sampling strategy ... p_{t,H_1} = 1/(buffer size)".
* **H2** (capacity N2, paper "N_2 = batch size x 100") holds transitions that were
  sampled from H1 and used in a gradient step: "transitions move to H_2 with another
  weight p_{t,H_2} ... H_2 is equivalent to transitions sampled from H_1 used to
  construct models". Each entry carries a weight p, sampled with probability
  p / sum(p) through a :class:`SumTree`.

Batches. "When H_2 complies an adequate amount of transitions to train, we sample from
both H_1 and H_2 ... with the parameter lambda ... if lambda = 0.1, it means taking 90% of
train data from H_1 and only 10% of data from H_2." Until H2 holds ``h2_min_size``
transitions every row comes from H1; afterwards every batch of B rows has exactly
``n2 = floor(lambda * B + 0.5)`` (round half up) rows from H2 and ``B - n2`` from H1, H1
rows first. lambda = 0 is uniform DQN; lambda = 1 takes only H2 once it is ready. The one
exception: if H1 is empty (every transition was moved out and nothing new was added)
the H1 share is drawn from H2; ``replay/h2_fraction`` reports it.

Promotion (on :meth:`update_priorities`, i.e. after the gradient step that used the
batch). Each distinct H1 transition of the batch is put into H2 with probability
``p_promote`` ("put used transition into H_2 with probability p_t"), with the weight
"p_{t,H_2} = e^{|delta_t|}", delta_t its TD error in that step. ``promote_mode='move'``
removes it from H1 ("transitions move to H_2"); ``'copy'`` leaves it in H1 too.
With lambda = 0 nothing is promoted: H2 would never be read, and moving would only
drain H1, while lambda = 0 must be plain uniform DQN ("if lambda equals to 0, means
uniformly sampling from DQN").
Note on 'move' with p_promote = 1: every H1 row of every batch leaves H1, about
(1 - lambda) x B per gradient step, while one transition arrives per env step; H1 then
holds only transitions no gradient step has used yet (a few), and its share of each
batch repeats them. ``'copy'`` keeps H1 a full N1 window: the library default and every
shipped config. ``'move'`` stays available as the authors' rule (their code pops from H1,
but trains once per episode, where the drain does not arise).

Weight update, eq. 3. The H2 transitions of a batch get "p <- p^{w_t}, where
w_t = delta_t^2 / sum_n delta_n^2", the sum over the batch's H2 transitions
(``eq3_sum='h2'``, the default) or over all rows of the batch (``eq3_sum='batch'``) --
the paper does not say which. Since w_t <= 1 and p >= 1, weights fall towards 1 ("the
frequently sampled transitions converge to 1 which is the baseline"). If every delta in
the sum is 0, w is 0/0 and the weights are left unchanged. There is no importance-sampling
correction: every returned weight is 1.0 ("we predefine the diminishing weight rules to
decrease bias in place of important sampling methods like the PER").

Numerics. Weights are kept as log p: log p = min(|delta|, max_log_weight) at promotion,
log p <- w * log p at eq. 3, so e^{|delta|} never overflows; the sum tree holds
exactly exp(log p) <= exp(max_log_weight). NaN or inf TD errors raise ``ValueError``
(the learner has diverged; nothing is changed). w is computed from delta / max|delta|,
so |delta| up to 1e308 cannot overflow delta^2.

Duplicates. H1 and H2 are both sampled with replacement, so a batch may hold one
transition twice. Every rule is applied once per distinct transition, with the TD error
of its last row (a DQN step gives all copies the same delta); the eq. 3 sum with
``eq3_sum='h2'`` runs over the distinct H2 transitions, with ``'batch'`` over every row.

H1 storage. H1 is a ring of N1 slots written in FIFO order: each new transition takes the
slot written N1 additions ago, evicting its content if it is still there. So H1 is "the
last N1 transitions added, minus those moved to H2"; moving leaves a hole that is reused
when the ring comes round. The live slots are also kept in a dense array (with each
slot's position in it), so moving k transitions out costs O(k) (the live slots at the
end of the dense array fill the holes) and uniform sampling draws positions from the
dense array: exact over the live transitions.

H2 eviction when full: ``h2_eviction='fifo'`` replaces the oldest entry (ring order);
``'min_weight'`` replaces the entries with the smallest weight, i.e. the most replayed
ones (their p is closest to the baseline 1).

Handles. ``Batch.indices`` are int64 ``slot | generation << 33`` with H1 at slots
[0, N1) and H2 at [N1, N1 + N2) of one shared storage; each slot
counts its writes and moves, so a handle whose slot was overwritten or moved since it was
sampled is ignored by :meth:`update_priorities` instead of touching the wrong transition.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError, validate
from der_ros.replay.base import Batch, ReplayBuffer, check_batch_size, check_td_errors
from der_ros.replay.config import ReplayConfig
from der_ros.replay.double_replay_kernels import dense_remove, der_plan
from der_ros.replay.storage import RingStorage, describe, storage_bytes
from der_ros.replay.storage import check_memory as _check_memory
from der_ros.replay.sum_tree import SumTree

__all__ = ["DoubleReplay", "h2_split"]

_GEN_MASK = np.int64((1 << 30) - 1)


def _bump(gen: np.ndarray, slots: np.ndarray) -> None:
    """Advance the write generation of distinct ``slots`` (kept below 2**30 so handles fit in int64)."""
    gen[slots] = (gen.take(slots) + 1) & _GEN_MASK


def h2_split(lam: float, batch_size: int) -> int:
    """Rows of a batch taken from H2 once it is ready: round(lambda * B), halves rounded up."""
    return int(math.floor(lam * batch_size + 0.5))


class DoubleReplay(ReplayBuffer):
    """DER: H1 (uniform, N1) + H2 (weighted by p, N2) with promotion and eq. 3 updates.

    ``cfg`` is a ``kind='der'`` :class:`ReplayConfig` with ``h2_capacity`` and ``h2_min_size``
    resolved (:func:`der_ros.replay.factory.make_replay` fills in the batch-size defaults); it is
    validated once here, by the same rules as a config file (field ranges and ``check()``).
    """

    kind = "der"

    def __init__(
        self,
        cfg: ReplayConfig,
        obs_shape: Sequence[int],
        obs_dtype: np.dtype | str | type = np.float32,
        seed: int | None = 0,
        check_memory: bool = True,
        available_bytes: int | None = None,
    ) -> None:
        for name in ("h2_capacity", "h2_min_size"):
            if getattr(cfg, name) is None:
                raise ConfigError(f"replay: {name} = None; DoubleReplay needs it resolved (make_replay does that)")
        cfg = validate(dataclasses.replace(cfg), "replay")
        if cfg.kind != self.kind:
            raise ConfigError(f"replay: kind = {cfg.kind!r}, expected {self.kind!r} for DoubleReplay")
        capacity, h2_capacity = int(cfg.capacity), int(cfg.h2_capacity)
        if check_memory:
            needed = storage_bytes(capacity, obs_shape, obs_dtype) + storage_bytes(h2_capacity, obs_shape, obs_dtype)
            what = f"H1 {describe(capacity, obs_shape, obs_dtype)} + H2 (h2_capacity={h2_capacity})"
            _check_memory(needed, what, available_bytes)
        self.capacity = capacity
        self.h2_capacity = h2_capacity
        self.lam = float(cfg.lam)
        self.h2_min_size = int(cfg.h2_min_size)
        self.p_promote = float(cfg.p_promote)
        self.promote_mode = cfg.promote_mode
        self.h2_eviction = cfg.h2_eviction
        self.eq3_sum = cfg.eq3_sum
        self.max_log_weight = float(cfg.max_log_weight)
        self._rng = np.random.default_rng(seed)

        n1, n2 = self.capacity, self.h2_capacity
        # One storage for both memories (slots [0, N1) are H1, [N1, N1 + N2) are H2), so a
        # mixed batch is one take per field; h1/h2 are views with their own ring cursors.
        self.store = RingStorage(n1 + n2, obs_shape, obs_dtype)
        self.h1 = self.store.view(0, n1)
        self.h2 = self.store.view(n1, n1 + n2)
        self._gen = np.zeros(n1 + n2, dtype=np.int64)  # write generation per global slot
        self.h1_live = np.zeros(n1, dtype=np.int64)  # dense list of live slots, first h1_size valid
        self.h1_pos = np.full(n1, -1, dtype=np.int64)  # slot -> position in h1_live, -1 = empty
        self.h1_gen = self._gen[:n1]
        self.h1_size = 0

        self.h2_tree = SumTree(n2)
        self.h2_logw = np.zeros(n2, dtype=np.float64)
        self.h2_gen = self._gen[n1:]
        self.h2_size = 0
        # scratch for de-duplicating the rows of a batch in O(B) (see double_replay_kernels.der_plan)
        self._h1_mark = np.zeros(n1, dtype=np.int64)
        self._h2_mark = np.zeros(n2, dtype=np.int64)
        #: transitions promoted H1 -> H2 so far, and the H2 share of the last batch
        self.promoted = 0
        self.last_h2_fraction = 0.0

    # ------------------------------------------------------------------ writing
    def add_batch(self, obs, actions, rewards, next_obs, terminated, truncated) -> None:  # noqa: D102
        fields = self.h1.convert(obs, actions, rewards, next_obs, terminated, truncated)
        k = fields[0].shape[0]
        if k > self.capacity:  # in ring-sized chunks: the same state as k add() calls
            for start in range(0, k, self.capacity):
                self._add_converted(tuple(f[start : start + self.capacity] for f in fields))
            return
        self._add_converted(fields)

    def _add_converted(self, fields: tuple[np.ndarray, ...]) -> None:
        k = fields[0].shape[0]
        slots = self.h1.next_slots(k)
        self.h1.write(slots, fields)
        _bump(self.h1_gen, slots)  # invalidates handles to whatever was there
        new = slots[self.h1_pos.take(slots) < 0]
        if new.size:
            n = self.h1_size
            self.h1_live[n : n + new.size] = new
            self.h1_pos[new] = np.arange(n, n + new.size, dtype=np.int64)
            self.h1_size = n + new.size

    def add(self, obs, action, reward, next_obs, terminated, truncated) -> None:  # noqa: D102
        slot = self.h1.cursor
        self.h1.put_one(slot, obs, action, reward, next_obs, terminated, truncated)
        self.h1.next_slot()
        self.h1_gen[slot] = (self.h1_gen[slot] + 1) & _GEN_MASK
        if self.h1_pos[slot] < 0:
            self.h1_live[self.h1_size] = slot
            self.h1_pos[slot] = self.h1_size
            self.h1_size += 1

    def _newest_slot(self) -> tuple[RingStorage, int]:
        return self.h1, (self.h1.cursor - 1) % self.capacity

    # ------------------------------------------------------------------ sampling
    def sample(self, batch_size: int) -> Batch:
        check_batch_size(batch_size, self.capacity + self.h2_capacity, self.h1_size + self.h2_size)
        B = int(batch_size)
        n2 = h2_split(self.lam, B) if self.h2_size >= self.h2_min_size else 0
        if self.h1_size == 0:  # everything moved out: only H2 can serve
            n2 = B
        n1 = B - n2
        rng = self._rng
        slots = np.empty(B, dtype=np.int64)  # global slots: H1 rows first, then H2 rows
        if n1:
            self.h1_live.take(rng.integers(0, self.h1_size, n1, dtype=np.int64), out=slots[:n1])
        if n2:
            np.add(self.h2_tree.sample(rng, n2, limit=self.h2_size, positive=True), self.capacity, out=slots[n1:])
        out = self.store.gather(slots)
        indices = slots | self._gen.take(slots) << 33
        source = np.zeros(B, dtype=np.uint8)
        source[n1:] = 1
        self.last_h2_fraction = n2 / B
        return Batch(*out, indices, np.ones(B, dtype=np.float32), source)

    # ------------------------------------------------------------------ updates
    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """Eq. 3 on the batch's H2 transitions, then promotion of its H1 transitions (see module doc)."""
        idx, td = check_td_errors(indices, td_errors)
        if idx.size == 0:
            return
        absd = np.abs(td)
        # validity, de-duplication and eq. 3 (writes h2_logw) in one pass
        s2, lw2, s1, d1 = der_plan(
            idx, absd, self.capacity, self.h1_gen, self.h1_pos, self.h2_gen, self.h2_size, self._h1_mark, self._h2_mark,
            self.eq3_sum == "batch", self.h2_logw, self.h2_tree.use_numba,
        )  # fmt: skip
        if self.lam > 0.0 and s1.size:
            if self.p_promote < 1.0:
                keep = self._rng.random(s1.size) < self.p_promote
                s1, d1 = s1[keep], d1[keep]
            if s1.size:
                dst, lw1 = self._promote(s1, d1)
                if s2.size:  # eq. 3 first, promotions last: a promotion that evicts an entry updated above wins
                    s2, lw2 = np.concatenate([s2, dst]), np.concatenate([lw2, lw1])
                else:
                    s2, lw2 = dst, lw1
        if s2.size:
            self.h2_tree.set(s2, np.exp(lw2), check=False)

    def _promote(self, slots1: np.ndarray, absd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Copy H1 ``slots1`` into H2 with log p = min(|delta|, cap); returns (H2 slots, log p)."""
        k = slots1.size
        if k > self.h2_capacity:  # only the last N2 would survive anyway
            slots1, absd = slots1[k - self.h2_capacity :], absd[k - self.h2_capacity :]
            k = self.h2_capacity
        dst = self._h2_slots(k)
        gdst = dst + self.capacity
        self.store.resolve_among(slots1)  # (a sampled transition was completed when its batch was gathered)
        for arr in self.store.arrays_tuple:
            arr[gdst] = arr.take(slots1, axis=0)
        logw = np.minimum(absd, self.max_log_weight)
        self.h2_logw[dst] = logw
        _bump(self.h2_gen, dst)
        self.promoted += k
        if self.promote_mode == "move":
            self.h1_size = dense_remove(
                self.h1_live, self.h1_pos, self.h1_gen, slots1, self.h1_size, int(_GEN_MASK), self.h2_tree.use_numba
            )
        return dst, logw

    def _h2_slots(self, k: int) -> np.ndarray:
        """H2 slots for k new entries, evicting by the configured rule when H2 is full."""
        if self.h2_eviction == "fifo":
            dst = self.h2.next_slots(k)
            self.h2_size = min(self.h2_size + k, self.h2_capacity)
            return dst
        free = self.h2_capacity - self.h2_size
        if k <= free:
            dst = np.arange(self.h2_size, self.h2_size + k, dtype=np.int64)
        else:
            m = k - free
            leaves = self.h2_tree.leaves[: self.h2_size]
            evict = np.argpartition(leaves, m - 1)[:m] if m < self.h2_size else np.arange(self.h2_size)
            dst = np.concatenate([np.arange(self.h2_size, self.h2_capacity, dtype=np.int64), evict.astype(np.int64)])
        self.h2_size = min(self.h2_size + k, self.h2_capacity)
        self.h2.num_written += k
        return dst

    # ------------------------------------------------------------------ info
    def __len__(self) -> int:
        return self.h1_size + self.h2_size

    def h2_weights(self) -> np.ndarray:
        """Weights p = exp(log p) of the H2 entries (a copy, in slot order)."""
        return np.exp(self.h2_logw[: self.h2_size])

    def stats(self) -> dict[str, float]:
        """``replay/size`` (H1 + H2), ``replay/h1_size``, ``replay/h2_size``, ``replay/h2_fraction``
        (H2 share of the last batch), ``replay/h2_weight_mean`` / ``_max`` (of p over H2; 0 while
        H2 is empty), ``replay/promoted`` (H1 -> H2 promotions so far)."""
        if self.h2_size:
            leaves = self.h2_tree.leaves[: self.h2_size]
            mean, wmax = float(leaves.mean()), float(leaves.max())
        else:
            mean = wmax = 0.0
        return {
            "replay/size": float(len(self)),
            "replay/h1_size": float(self.h1_size),
            "replay/h2_size": float(self.h2_size),
            "replay/h2_fraction": float(self.last_h2_fraction),
            "replay/h2_weight_mean": mean,
            "replay/h2_weight_max": wmax,
            "replay/promoted": float(self.promoted),
        }

    def set_lam(self, lam: float) -> None:
        """Change lambda while learning (the agent node's mutable ``replay.lam``)."""
        if not 0.0 <= lam <= 1.0:
            raise ConfigError(f"replay: lam = {lam!r}, expected >= 0.0 and <= 1.0")
        self.lam = float(lam)

    # ------------------------------------------------------------------ state
    def config(self) -> ReplayConfig:
        """The (resolved) :class:`ReplayConfig` this buffer runs with."""
        kw = self._ctor_kwargs()
        return ReplayConfig(kind=self.kind, **{k: v for k, v in kw.items() if k not in ("obs_shape", "obs_dtype")})

    @classmethod
    def from_ctor_kwargs(cls, kwargs: dict[str, Any]) -> DoubleReplay:  # noqa: D102
        kw = dict(kwargs)
        obs_shape, obs_dtype = kw.pop("obs_shape"), kw.pop("obs_dtype")
        return cls(ReplayConfig(kind=cls.kind, **kw), obs_shape, obs_dtype, check_memory=False)

    def _ctor_kwargs(self) -> dict[str, Any]:
        return {
            "capacity": self.capacity,
            "h2_capacity": self.h2_capacity,
            "obs_shape": list(self.h1.obs_shape),
            "obs_dtype": self.h1.obs_dtype.str,
            "lam": self.lam,
            "h2_min_size": self.h2_min_size,
            "p_promote": self.p_promote,
            "promote_mode": self.promote_mode,
            "h2_eviction": self.h2_eviction,
            "eq3_sum": self.eq3_sum,
            "max_log_weight": self.max_log_weight,
        }

    def _arrays(self) -> dict[str, np.ndarray]:
        out = self.h1.arrays("h1")
        out.update(self.h2.arrays("h2"))
        out["h1/live"] = self.h1_live
        out["h1/pos"] = self.h1_pos
        out["h1/gen"] = self.h1_gen
        out["h2/logw"] = self.h2_logw
        out["h2/gen"] = self.h2_gen
        out["h2/tree_leaves"] = self.h2_tree.leaves
        out["counters"] = np.array([self.h1_size, self.h2_size, self.promoted], dtype=np.int64)
        out["last_h2_fraction"] = np.array(self.last_h2_fraction, dtype=np.float64)
        return out

    def _set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self.h1.set_arrays(arrays, "h1")
        self.h2.set_arrays(arrays, "h2")
        self.h1_live[...] = arrays["h1/live"]
        self.h1_pos[...] = arrays["h1/pos"]
        self.h1_gen[...] = arrays["h1/gen"]
        self.h2_logw[...] = arrays["h2/logw"]
        self.h2_gen[...] = arrays["h2/gen"]
        self.h2_tree.leaves[...] = arrays["h2/tree_leaves"]
        self.h2_tree.rebuild()
        self.h1_size, self.h2_size, self.promoted = (int(x) for x in arrays["counters"])
        self.last_h2_fraction = float(arrays["last_h2_fraction"])
