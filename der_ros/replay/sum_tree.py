"""SumTree: proportional sampling over non-negative leaf values in O(log N).

Layout. The leaves are split into ``R`` (a power of two, <= ``root_width``) complete
binary sum trees of equal height ``h``, stored level by level in one flat float64 array
``nodes`` (``levels`` are views into it): ``levels[0]`` holds the R roots, ``levels[h]`` the leaves, and node ``j`` of level ``d``
has children ``2j`` and ``2j + 1`` in level ``d + 1``. Every internal node is always
recomputed as ``left + right`` from its children (never updated by a delta), so values
depend only on the leaves: no rounding drift, and saving the leaves is enough to restore
the tree bit for bit.

Why a forest and not one tree: in numpy the work per call is dominated by the number of
Python-level operations, i.e. by the number of levels. The top of the tree is replaced by
one prefix sum over the R roots plus one binary search per sample, which removes
``log2 R`` levels from both the descent and every update. The descent and the updates
run as compiled numba kernels when numba is installed and as vectorised numpy (all B
samples one level at a time) otherwise, with bit-identical results
(:mod:`der_ros.replay.sum_tree_kernels`).

Sampling (:meth:`sample`) is stratified as in Schaul et al. (2015): the range
``[0, total)`` is cut into B equal segments and one value is drawn in each. Every
descent is clamped so it can never return a zero-valued leaf (rounding at segment
boundaries) or a leaf at or past ``limit`` (the filled size of a buffer).

Measured on the numpy path (numpy 2.4, one core): a cumsum costs ~3.5 ns per root and a
level ~2 us per call, so R = 1024 balances the two; a 50,000-leaf tree has height 6.
"""

from __future__ import annotations

import numpy as np

from der_ros.replay.sum_tree_kernels import HAVE_NUMBA, tree_find, tree_propagate, tree_sample

__all__ = ["SumTree"]


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n) - 1).bit_length()


class SumTree:
    """Sum tree over ``capacity`` non-negative float64 leaves (all start at 0).

    All levels live in one flat array ``nodes`` (level d at ``offsets[d]``), so the
    compiled kernels of :mod:`der_ros.replay.sum_tree_kernels` can walk it; ``levels`` are views.
    """

    def __init__(self, capacity: int, root_width: int = 1024, use_numba: bool | None = None) -> None:
        if int(capacity) <= 0:
            raise ValueError(f"SumTree capacity = {capacity}, expected >= 1")
        if root_width <= 0 or root_width & (root_width - 1):
            raise ValueError(f"root_width = {root_width}, expected a power of two")
        self.capacity = int(capacity)
        n_leaves = _next_pow2(self.capacity)
        self.n_roots = min(n_leaves, int(root_width))
        self.height = (n_leaves // self.n_roots).bit_length() - 1
        sizes = [self.n_roots << d for d in range(self.height + 1)]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.nodes = np.zeros(int(self.offsets[-1]), dtype=np.float64)
        self.levels = [self.nodes[self.offsets[d] : self.offsets[d + 1]] for d in range(self.height + 1)]
        self.leaves = self.levels[-1]
        self._leaf_offset = int(self.offsets[self.height])
        self.use_numba = HAVE_NUMBA if use_numba is None else bool(use_numba and HAVE_NUMBA)

    # ------------------------------------------------------------------ values
    @property
    def total(self) -> float:
        return float(self.levels[0].sum())

    def get(self, idx: np.ndarray) -> np.ndarray:
        return self.leaves.take(idx)

    def set(self, idx: np.ndarray, values: np.ndarray, check: bool = True) -> None:
        """Set leaves ``idx`` to ``values`` (finite, >= 0) and recompute their ancestors.

        Duplicate indices are allowed; the last value wins (as in numpy assignment).
        ``check=False`` skips the range/finiteness checks for callers that already did them
        (this is on the hot path of every gradient step).
        """
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if idx.size == 0:
            return
        if check:
            if idx.shape != values.shape:
                raise ValueError(f"SumTree.set: {idx.size} indices but {values.size} values")
            if idx.min() < 0 or idx.max() >= self.capacity:
                raise IndexError(f"SumTree leaf index out of range [0, {self.capacity}): {idx.min()}..{idx.max()}")
            ok = np.isfinite(values) & (values >= 0)
            if not ok.all():
                raise ValueError(f"SumTree values must be finite and >= 0, got {values[~ok][:3]}")
        self.leaves[idx] = values
        tree_propagate(self.nodes, self.offsets, self.n_roots, self.height, idx, self.use_numba)

    def rebuild(self) -> None:
        """Recompute every internal node from the leaves (after bulk leaf writes)."""
        for d in range(self.height, 0, -1):
            self.levels[d - 1][:] = self.levels[d].reshape(-1, 2).sum(axis=1)

    def max(self, limit: int | None = None) -> float:
        n = self.capacity if limit is None else int(limit)
        return float(self.leaves[:n].max()) if n > 0 else 0.0

    # ------------------------------------------------------------------ sampling
    def find(self, u: np.ndarray, limit: int | None = None, positive: bool = False) -> np.ndarray:
        """Leaf index whose prefix-sum interval contains each ``u`` (0 <= u < total).

        Never returns an index >= ``limit`` (default: capacity), nor a zero leaf unless
        ``positive=True`` promises that every leaf below ``limit`` is > 0 (true for the
        buffers: PER priorities are >= eps^alpha, DER weights >= 1).
        """
        u = np.ascontiguousarray(u, dtype=np.float64).reshape(-1)
        limit = self.capacity if limit is None else int(limit)
        j = tree_find(self.nodes, self.offsets, self.n_roots, self.height, u, limit, self.use_numba)
        if positive:
            return j
        # rounding at a boundary can step into a zero leaf: move to the nearest non-zero one
        bad = self.leaves.take(j) <= 0.0
        if bad.any():
            j[bad] = self._nearest_nonzero(j[bad], limit)
        return j

    def _nearest_nonzero(self, j: np.ndarray, limit: int) -> np.ndarray:
        """Rare path: the closest non-zero leaf at or below ``j`` (else above), below ``limit``."""
        nz = np.flatnonzero(self.leaves[:limit] > 0.0)
        if nz.size == 0:
            raise ValueError("cannot sample from a SumTree whose leaves are all zero")
        k = np.searchsorted(nz, j, side="right") - 1
        return nz[np.maximum(k, 0)]

    def sample(
        self, rng: np.random.Generator, n: int, limit: int | None = None, positive: bool = False
    ) -> np.ndarray:
        """``n`` leaf indices drawn with probability leaf / total, stratified over ``[0, total)``
        (one uniform draw in each of n equal segments, Schaul et al. 2015)."""
        r = rng.random(n)
        limit = self.capacity if limit is None else int(limit)
        j = tree_sample(self.nodes, self.offsets, self.n_roots, self.height, r, limit, self.use_numba)
        if positive:
            return j
        bad = self.leaves.take(j) <= 0.0  # rounding at a boundary, or an all-zero tree
        if bad.any():
            j[bad] = self._nearest_nonzero(j[bad], limit)
        return j
