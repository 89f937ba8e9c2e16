"""Shared set-up of the Ray tests: loopback only, no token written to ~/.ray, no usage stats.

Every Ray process a test starts binds to 127.0.0.1: the local instances through
:func:`der_ros.experiments.backends.ray_cluster.loopback_ray`, the ``ray start`` nodes of the
two-node test through the same switch in their environment.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[1]
CARTPOLE = REPO / "config" / "cartpole.yaml"
LOOPBACK = {"127.0.0.1", "::ffff:127.0.0.1"}


def ray_test_env(mp: pytest.MonkeyPatch) -> dict[str, str]:
    """Env of a test Ray: the session's token (conftest.py; Ray would otherwise write one to
    ~/.ray/auth_token), single-machine mode (loopback), no usage statistics, no cluster address."""
    assert os.environ.get("RAY_AUTH_MODE") == "token" and os.environ.get("RAY_AUTH_TOKEN"), "set by conftest.py"
    mp.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    mp.setenv("RAY_USAGE_STATS_ENABLED", "0")
    mp.delenv("RAY_ADDRESS", raising=False)
    return dict(os.environ)


def ray_listening_addresses() -> set[str]:
    """IP addresses on which Ray processes started by this test process listen (TCP)."""
    me = psutil.Process()
    pids = set()
    for child in me.children(recursive=True):
        try:
            if "ray" in " ".join(child.cmdline()):
                pids.add(child.pid)
        except psutil.Error:
            continue
    return {c.laddr.ip for c in psutil.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN and c.pid in pids}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def small_cartpole(steps: int, **extra: object) -> dict[str, object]:
    out: dict[str, object] = {"train.total_steps": steps, "agent.learning_starts": 100, "agent.hidden_sizes": [32],
                              "train.tensorboard": False, "train.eval_interval": 100, "train.eval_episodes": 3,
                              "train.final_eval_episodes": 4}  # fmt: skip
    out.update(extra)
    return out
