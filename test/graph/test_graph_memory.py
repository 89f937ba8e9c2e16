"""Bounded memory of a long ``der graph`` run (issue 45, finding 4): what the runner and the bridge
keep per step or per episode is bounded by a constant, checked on the containers themselves.

The RSS of a real long run is measured by ``bench/soak.py`` (figures in bench/README.md).
"""

from __future__ import annotations

import ctypes
import tracemalloc
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ros_harness import ros_domain  # noqa: F401 - fixture

from der_ros.contract import EPISODE_COLLISION, EPISODE_START, EPISODE_SUCCESS, episode_values

#: the recent-returns window of der_ros.graph.run_progress (checked equal in the first test)
RECENT_RETURNS = 1000
_CONTAINERS = (list, dict, set, deque, tuple)


def _sizes(obj: Any, path: str = "", depth: int = 3) -> Iterator[tuple[str, int]]:
    """(attribute path, length) of every container held by ``obj`` and by the der_ros objects it holds."""
    if depth < 0:
        return
    for name, value in vars(obj).items():
        if isinstance(value, _CONTAINERS):
            yield f"{path}{name}", len(value)
        elif type(value).__module__.startswith("der_ros") and hasattr(value, "__dict__"):
            yield from _sizes(value, f"{path}{name}.", depth - 1)


def _episodes(n: int, start: int = 0) -> Iterator[tuple[str, dict[str, object]]]:
    for ep in range(start, start + n):
        yield EPISODE_START, episode_values(ep, 0, ret=None)
        yield (EPISODE_SUCCESS if ep % 3 else EPISODE_COLLISION), episode_values(ep, 4, float(ep % 7), ep % 2, 12.5)


def test_the_progress_counter_keeps_counts_and_recent_returns_only() -> None:
    from der_ros.graph import run_progress as progress

    assert progress.RECENT_RETURNS == RECENT_RETURNS
    counts = progress.ProgressCounter()
    n = 3 * RECENT_RETURNS
    for event, values in _episodes(n):
        counts.add_event(event, values)
        counts.add_step()
    snap = counts.snapshot()
    assert (snap.episodes, snap.steps) == (n, 2 * n)
    assert snap.outcomes[EPISODE_COLLISION] == n // 3 and snap.outcomes[EPISODE_SUCCESS] == n - n // 3
    assert snap.lane_changes == n // 2
    assert snap.returns == [float(ep % 7) for ep in range(n - RECENT_RETURNS, n)]
    assert snap.mean_return(10) == pytest.approx(sum(ep % 7 for ep in range(n - 10, n)) / 10)
    assert max(size for _name, size in _sizes(counts)) <= RECENT_RETURNS


@pytest.mark.ros
def test_the_graph_monitor_holds_bounded_state_over_many_episodes(ros_domain: int) -> None:  # noqa: F811
    """The runner's monitor fed 6,000 episodes through its own callbacks: no container it holds grows
    past the recent-returns window, and another 4,000 episodes allocate (almost) nothing that stays."""
    from der_ros.graph.monitor import GraphMonitor  # lazy: rclpy
    from der_ros.nodes import msg_conversions as mc

    monitor = GraphMonitor(ros_domain)
    try:
        msgs = [mc.make_episode_event(i, event, values) for i, (event, values) in enumerate(_episodes(500))]

        def feed(rounds: int) -> None:
            for _ in range(rounds):
                for msg in msgs:
                    monitor._on_episode(msg)
                    monitor._on_cmd(None)

        feed(12)
        sizes = dict(_sizes(monitor))
        assert max(sizes.values()) <= RECENT_RETURNS, sizes
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            feed(8)
            grown = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
        assert grown < 64 * 1024, f"{grown} bytes kept after 4,000 more episodes"
        snap = monitor.snapshot()
        assert snap.episodes == 10_000 and snap.steps == 20_000
    finally:
        monitor.close()


def _rss_kb() -> int:
    """This process's resident set (kB), after handing freed heap back to the kernel."""
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


def test_the_bridge_latency_ring_is_resident_from_the_start() -> None:
    """The bridge's round-trip ring takes its memory when it is made, not a page at a time as steps
    fill it (8 bytes a step until full: the bridge's RSS grew with every step)."""
    from der_ros.nodes.bridge_node import LatencyStats  # rclpy-free class in a node module

    stats = LatencyStats(200_000)
    before = _rss_kb()
    for i in range(200_000):
        stats.add(1_000_000 + i)
    grown = _rss_kb() - before
    assert grown < 400, f"RSS grew {grown} kB while 1.6 MB of round trips were written"
    assert len(stats) == 200_000
    for _ in range(200_000):  # a second lap: the ring holds the newest only
        stats.add(5_000_000)
    assert stats.percentiles_ms()["roundtrip_p50_ms"] == 5.0 and stats.percentiles_ms()["roundtrip_n"] == 200_000
