"""Greedy policies and their snapshots: argmax Q over a batch of observations, and the small
weight files the ROS agent node writes so that ``der graph`` can evaluate while it trains."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "Policy",
    "GreedyQPolicy",
    "net_state",
    "save_policy",
    "load_policy",
    "policy_files",
]

#: A batched policy: (observations (B, ...), infos of those B envs) -> B actions.
Policy = Callable[[np.ndarray, Sequence[dict[str, Any]]], Sequence[int]]


class GreedyQPolicy:
    """argmax_a Q(s, a) of a Q-network (epsilon = 0), batched."""

    def __init__(self, net: Any, obs_dtype: np.dtype, use_mask: bool = False) -> None:
        import torch

        self._torch = torch
        self.net = net
        self.obs_dtype = np.dtype(obs_dtype)
        #: a shield in mask mode: argmax over the actions ``info["action_mask"]`` allows
        self.use_mask = use_mask

    def __call__(self, obs: np.ndarray, infos: Sequence[dict[str, Any]]) -> Sequence[int]:
        torch = self._torch
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(obs, dtype=self.obs_dtype))
            q = self.net(x)
            if self.use_mask:
                allowed = torch.from_numpy(np.stack([np.asarray(i["action_mask"], dtype=bool) for i in infos]))
                q = q.masked_fill(~allowed, -math.inf)
            return q.argmax(1).tolist()


def net_state(net: Any) -> dict[str, np.ndarray]:
    """A picklable copy of a network's weights."""
    return {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}


POLICY_PREFIX = "policy_"


def save_policy(directory: str | Path, steps: int, net: Any) -> Path:
    """Write the Q-network's weights at ``steps`` as ``<directory>/policy_<steps>.npz`` (atomic).

    A few tens of kB: the ROS agent node writes one every ``policy_every`` steps so that ``der
    graph`` can evaluate the policy greedily in another process while the graph trains on.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{POLICY_PREFIX}{int(steps):09d}.npz"
    tmp = directory / f".{path.name}.tmp{os.getpid()}.npz"
    np.savez(tmp, **{f"w:{k}": v for k, v in net_state(net).items()}, steps=np.int64(steps))
    os.replace(tmp, path)
    return path


def load_policy(path: str | Path) -> tuple[int, dict[str, np.ndarray]]:
    """(steps, weights) of a file written by :func:`save_policy`."""
    with np.load(Path(path), allow_pickle=False) as data:
        state = {k[2:]: data[k] for k in data.files if k.startswith("w:")}
        return int(data["steps"]), state


def policy_files(directory: str | Path) -> list[Path]:
    """The policy snapshots of ``directory``, by step."""
    directory = Path(directory)
    return sorted(directory.glob(f"{POLICY_PREFIX}*.npz")) if directory.is_dir() else []
