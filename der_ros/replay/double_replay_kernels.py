"""DER's inner loops (paper eq. 3 and the H1 -> H2 promotion), compiled with numba when available.

Split from the sum-tree kernels because they implement :class:`~der_ros.replay.double_replay.DoubleReplay`'s
rules, not the tree's: :func:`der_plan` checks the batch's handles, de-duplicates the rows and
applies eq. 3 to the H2 rows in one pass; :func:`dense_remove` takes promoted ("moved")
transitions out of H1's dense list of live slots. Each has a numpy fallback that gives the
same result (``test_replay.py`` checks the two agree bit for bit).
"""

from __future__ import annotations

import numpy as np

from der_ros.replay._numba import HAVE_NUMBA, jit

__all__ = ["der_plan", "dense_remove"]


_SLOT_MASK = (1 << 32) - 1


def _der_plan_py(idx, absd, n1cap, h1_gen, h1_pos, h2_gen, h2_size, h1_mark, h2_mark, eq3_batch, s2, lw2, h2_logw, s1, d1):  # pragma: no cover - compiled
    """DER update plan for one batch (see DoubleReplay.update_priorities).

    Handles are ``global slot | generation << 33``; global slots below ``n1cap`` are H1.
    Keeps the rows whose handle is current, once per slot (its last row), in row order;
    H2 rows get their eq. 3 log-weight ``log p * w`` in ``lw2`` (also written to
    ``h2_logw``); H1 rows are listed in ``s1``/``d1`` for promotion. Returns (n2, n1);
    n2 = 0 when every delta of the eq. 3 sum is zero (w = 0/0: nothing changes).
    """
    n = idx.shape[0]
    for i in range(n):  # pass 1: validity + last-row marker
        h = idx[i]
        slot = h & _SLOT_MASK
        gen = h >> 33
        if slot >= n1cap:
            loc = slot - n1cap
            if loc < h2_size and h2_gen[loc] == gen:
                h2_mark[loc] = i
        elif h1_pos[slot] >= 0 and h1_gen[slot] == gen:
            h1_mark[slot] = i
    n1 = 0
    n2 = 0
    for i in range(n):  # pass 2: keep each valid slot at its last row
        h = idx[i]
        slot = h & _SLOT_MASK
        gen = h >> 33
        if slot >= n1cap:
            loc = slot - n1cap
            if loc < h2_size and h2_gen[loc] == gen and h2_mark[loc] == i:
                s2[n2] = loc
                lw2[n2] = absd[i]
                n2 += 1
        elif h1_pos[slot] >= 0 and h1_gen[slot] == gen and h1_mark[slot] == i:
            s1[n1] = slot
            d1[n1] = absd[i]
            n1 += 1
    if n2 == 0:
        return 0, n1
    # eq. 3: w = d^2 / sum d^2, computed on d / max d (no overflow), sums sequential
    scale = 0.0
    if eq3_batch:
        for i in range(n):
            scale = max(scale, absd[i])
    else:
        for k in range(n2):
            scale = max(scale, lw2[k])
    if not scale > 0.0:
        return 0, n1
    total = 0.0
    if eq3_batch:
        for i in range(n):
            r = absd[i] / scale
            total += r * r
    else:
        for k in range(n2):
            r = lw2[k] / scale
            total += r * r
    for k in range(n2):
        r = lw2[k] / scale
        w = r * r
        w /= total
        lw2[k] = h2_logw[s2[k]] * w
        h2_logw[s2[k]] = lw2[k]
    return n2, n1


def _dense_remove_py(live, pos, gen, slots, size, gen_mask):  # pragma: no cover - compiled
    """Remove distinct live ``slots`` from the dense list ``live[:size]``; bumps their
    generation; returns the new size. The holes the removed slots leave in front of the
    new end are filled, in order, by the still-live slots of the tail (same result as the
    numpy version)."""
    m = slots.shape[0]
    new_n = size - m
    holes = np.empty(m, dtype=np.int64)
    nh = 0
    for k in range(m):
        s = slots[k]
        p = pos[s]
        if p < new_n:
            holes[nh] = p
            nh += 1
        pos[s] = -1
        gen[s] = (gen[s] + 1) & gen_mask
    h = 0
    for q in range(new_n, size):
        t = live[q]
        if pos[t] >= 0:
            live[holes[h]] = t
            pos[t] = holes[h]
            h += 1
    return new_n


if HAVE_NUMBA:
    _der_plan_nb = jit(_der_plan_py)
    _dense_remove_nb = jit(_dense_remove_py)


def der_plan(
    idx: np.ndarray,
    absd: np.ndarray,
    n1cap: int,
    h1_gen: np.ndarray,
    h1_pos: np.ndarray,
    h2_gen: np.ndarray,
    h2_size: int,
    h1_mark: np.ndarray,
    h2_mark: np.ndarray,
    eq3_batch: bool,
    h2_logw: np.ndarray,
    use_numba: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(H2 slots, their new log-weights -- already written to ``h2_logw`` --, H1 slots to
    promote, their |delta|) for one batch; each slot once (its last row), stale handles dropped."""
    n = idx.shape[0]
    if use_numba:
        s2 = np.empty(n, dtype=np.int64)
        lw2 = np.empty(n, dtype=np.float64)
        s1 = np.empty(n, dtype=np.int64)
        d1 = np.empty(n, dtype=np.float64)
        n2, n1 = _der_plan_nb(idx, absd, n1cap, h1_gen, h1_pos, h2_gen, h2_size, h1_mark, h2_mark, eq3_batch,
                              s2, lw2, h2_logw, s1, d1)
        return s2[:n2], lw2[:n2], s1[:n1], d1[:n1]
    rows = np.arange(n, dtype=np.int64)
    slot = idx & _SLOT_MASK
    gen = idx >> 33
    in_h2 = slot >= n1cap
    # H2
    s2, lw2 = np.empty(0, dtype=np.int64), np.empty(0, dtype=np.float64)
    loc = slot - n1cap
    m = in_h2 & (loc < h2_size)
    m[m] = h2_gen.take(loc[m]) == gen[m]
    if m.any():
        s, r = loc[m], rows[m]
        h2_mark[s] = r
        keep = h2_mark.take(s) == r
        s, d = s[keep], absd[r[keep]]
        ref = absd if eq3_batch else d
        scale = ref.max()
        if scale > 0.0:
            rr = ref / scale
            total = np.cumsum(rr * rr)[-1]  # sequential, as in the compiled kernel
            w = d / scale
            w = w * w
            w /= total
            lw2 = h2_logw.take(s) * w
            h2_logw[s] = lw2
            s2 = s
    # H1
    m = ~in_h2
    m[m] = (h1_pos.take(slot[m]) >= 0) & (h1_gen.take(slot[m]) == gen[m])
    s, r = slot[m], rows[m]
    h1_mark[s] = r
    keep = h1_mark.take(s) == r
    return s2, lw2, s[keep], absd[r[keep]]


def dense_remove(live: np.ndarray, pos: np.ndarray, gen: np.ndarray, slots: np.ndarray, size: int,
                 gen_mask: int, use_numba: bool) -> int:
    """Remove distinct live ``slots`` from ``live[:size]`` in O(len(slots)); returns the new size.

    The compiled version swaps each removed slot with the last live one; the numpy version
    fills the holes in front with the live slots of the tail. Both leave the same set of
    live slots (the order inside ``live`` can differ, which only relabels uniform draws).
    """
    if use_numba:
        return int(_dense_remove_nb(live, pos, gen, slots, size, gen_mask))
    m = slots.size
    new_n = size - m
    p = pos.take(slots)
    pos[slots] = -1
    gen[slots] = (gen.take(slots) + 1) & gen_mask
    holes = p[p < new_n]
    tail = live[new_n:size]
    movers = tail[pos.take(tail) >= 0]
    live[holes] = movers
    pos[movers] = holes
    return new_n
