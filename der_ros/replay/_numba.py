"""numba for the replay kernels: used when importable and ``DER_ROS_NO_NUMBA`` is unset.

Both kernel modules (:mod:`~der_ros.replay.sum_tree_kernels`,
:mod:`~der_ros.replay.double_replay_kernels`) compile with the same options, so they agree on
what "compiled" means; each keeps a numpy fallback with bit-identical results.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["HAVE_NUMBA", "jit"]

_nb: Any = None
if not os.environ.get("DER_ROS_NO_NUMBA"):
    try:
        import numba as _nb
    except ImportError:  # pragma: no cover - numba is in requirements.txt
        log.info("numba not available; the replay kernels use their numpy implementations")

HAVE_NUMBA = _nb is not None


def jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit`` with the replay's options: cached on disk, no GIL, no bounds checks."""
    return _nb.njit(cache=True, nogil=True, boundscheck=False)(fn)
