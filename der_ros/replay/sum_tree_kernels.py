"""Compiled inner loops of the sum tree (numba), with the numpy versions as fallback.

The compiled and numpy versions perform the same float64 operations in the same order
(sequential prefix sum over the roots, ``u - left`` on each right turn, parents as
``left + right``), so they give bit-identical trees and indices: a buffer saved with one
loads and continues identically with the other. ``test_replay.py`` checks this.

numba is used when available (:mod:`der_ros.replay._numba`); kernels are compiled on first use
and cached next to this file (about a second, once). DER's own kernels (eq. 3, promotion) are
in :mod:`der_ros.replay.double_replay_kernels`.
"""

from __future__ import annotations

import numpy as np

from der_ros.replay._numba import HAVE_NUMBA, jit

__all__ = ["HAVE_NUMBA", "tree_find", "tree_sample", "tree_propagate"]


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


if HAVE_NUMBA:
    _descend = jit(_descend_py)
    _find_nb = jit(_find_py)
    _sample_nb = jit(_sample_py)
    _propagate_nb = jit(_propagate_py)


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
