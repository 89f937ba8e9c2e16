"""Compiled inner loops of the sum tree (numba), with the numpy versions as fallback.

The compiled and numpy versions perform the same float64 operations in the same order
(sequential prefix sum over the roots, ``u - left`` on each right turn, parents as
``left + right``), so they give bit-identical trees and indices: a buffer saved with one
loads and continues identically with the other. ``test_replay.py`` checks this.

numba is used when importable and ``DER_ROS_NO_NUMBA`` is unset; kernels are compiled on
first use and cached next to this file (about a second, once).
"""

from __future__ import annotations

import logging
import os

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["HAVE_NUMBA", "tree_find", "tree_sample", "tree_propagate", "der_plan", "dense_remove"]

_nb = None
if not os.environ.get("DER_ROS_NO_NUMBA"):
    try:
        import numba as _nb  # type: ignore[no-redef]
    except ImportError:  # pragma: no cover - numba is in requirements.txt
        log.info("numba not available; the replay sum tree uses its numpy implementation")

HAVE_NUMBA = _nb is not None


def _find_py(nodes, offsets, n_roots, height, u, limit, out):  # pragma: no cover - compiled
    """Per sample: search the root prefix sums, then descend ``height`` binary levels."""
    cum = np.empty(n_roots, dtype=np.float64)
    acc = 0.0
    for r in range(n_roots):
        acc += nodes[r]
        cum[r] = acc
    return _descend(nodes, offsets, n_roots, height, cum, u, limit, out)


def _sample_py(nodes, offsets, n_roots, height, r, limit, out):  # pragma: no cover - compiled
    """Stratified draws: u_i = (i + r_i) * total / n, clamped below total, then descend."""
    cum = np.empty(n_roots, dtype=np.float64)
    acc = 0.0
    for k in range(n_roots):
        acc += nodes[k]
        cum[k] = acc
    total = cum[n_roots - 1]
    n = r.shape[0]
    seg = total / n
    top = np.nextafter(total, 0.0)
    u = np.empty(n, dtype=np.float64)
    for i in range(n):
        u[i] = min((i + r[i]) * seg, top)
    return _descend(nodes, offsets, n_roots, height, cum, u, limit, out)


def _descend_py(nodes, offsets, n_roots, height, cum, u, limit, out):  # pragma: no cover - compiled
    for i in range(u.shape[0]):
        x = u[i]
        # first root with cum > x (np.searchsorted side='right')
        lo, hi = 0, n_roots
        while lo < hi:
            mid = (lo + hi) >> 1
            if cum[mid] > x:
                hi = mid
            else:
                lo = mid + 1
        j = min(lo, n_roots - 1)
        x = x - (cum[j] - nodes[j])
        for d in range(1, height + 1):
            j <<= 1
            left = nodes[offsets[d] + j]
            if x >= left:
                x -= left
                j += 1
        out[i] = min(j, limit - 1)
    return out


def _propagate_py(nodes, offsets, height, idx):  # pragma: no cover - compiled
    """Recompute every ancestor of the leaves ``idx`` as left + right."""
    for i in range(idx.shape[0]):
        j = idx[i]
        for d in range(height, 0, -1):
            j >>= 1
            base = offsets[d] + 2 * j
            nodes[offsets[d - 1] + j] = nodes[base] + nodes[base + 1]


_SLOT_MASK = (1 << 32) - 1
_SRC_BIT = 1 << 32


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
    _jit = _nb.njit(cache=True, nogil=True, boundscheck=False)
    _descend = _jit(_descend_py)
    _find_nb = _jit(_find_py)
    _sample_nb = _jit(_sample_py)
    _propagate_nb = _jit(_propagate_py)
    _der_plan_nb = _jit(_der_plan_py)
    _dense_remove_nb = _jit(_dense_remove_py)


def tree_find(
    nodes: np.ndarray, offsets: np.ndarray, n_roots: int, height: int, u: np.ndarray, limit: int, use_numba: bool
) -> np.ndarray:
    """Leaf index for each ``u`` (clamped below ``limit``); see :class:`SumTree`."""
    out = np.empty(u.shape[0], dtype=np.int64)
    if use_numba:
        return _find_nb(nodes, offsets, n_roots, height, u, limit, out)
    return _find_np(nodes, offsets, n_roots, height, np.cumsum(nodes[:n_roots]), u, limit, out)


def _find_np(nodes, offsets, n_roots, height, cum, u, limit, out):
    roots = nodes[:n_roots]
    j = np.searchsorted(cum, u, side="right")
    np.minimum(j, n_roots - 1, out=j)
    x = u - (cum.take(j) - roots.take(j))
    for d in range(1, height + 1):
        level = nodes[offsets[d] : offsets[d] + (n_roots << d)]
        j <<= 1
        left = level.take(j)
        right = x >= left
        x -= left * right
        j += right
    np.minimum(j, limit - 1, out=out)
    return out


def tree_sample(
    nodes: np.ndarray, offsets: np.ndarray, n_roots: int, height: int, r: np.ndarray, limit: int, use_numba: bool
) -> np.ndarray:
    """Stratified proportional draws: one in each of ``len(r)`` equal segments of [0, total),
    at offset ``r`` (uniform [0, 1) numbers) inside its segment."""
    out = np.empty(r.shape[0], dtype=np.int64)
    if use_numba:
        return _sample_nb(nodes, offsets, n_roots, height, r, limit, out)
    cum = np.cumsum(nodes[:n_roots])
    total = cum[-1]
    u = np.arange(r.shape[0], dtype=np.float64)
    u += r
    u *= total / r.shape[0]
    np.minimum(u, np.nextafter(total, 0.0), out=u)
    return _find_np(nodes, offsets, n_roots, height, cum, u, limit, out)


def tree_propagate(nodes: np.ndarray, offsets: np.ndarray, n_roots: int, height: int, idx: np.ndarray,
                   use_numba: bool) -> None:
    """Recompute the ancestors of leaves ``idx`` (int64) after the leaves were written."""
    if use_numba:
        _propagate_nb(nodes, offsets, height, idx)
        return
    for d in range(height, 0, -1):
        idx = idx >> 1
        child = nodes[offsets[d] : offsets[d] + (n_roots << d)]
        pair = child.reshape(-1, 2).take(idx, axis=0)
        nodes[offsets[d - 1] + idx] = pair[:, 0] + pair[:, 1]


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
