"""RecorderConfig: the recorder node's parameters (ROS-free, so ``der graph`` can read defaults)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from der_ros.configuration import ConfigError, param
from der_ros.contract import default_record_topics

__all__ = ["RecorderConfig", "default_bag_path"]


def default_bag_path(root: str | Path = "runs/bags") -> Path:
    """``runs/bags/<UTC time>`` (microseconds keep two recorders started together apart)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime()) + f"-{int(time.time() * 1e6) % 1_000_000:06d}"
    return Path(root) / stamp


@dataclass
class RecorderConfig:
    """What the recorder subscribes to and how it writes the bag (see ``der_ros.bag.writer``)."""

    output: str = param("", "bag directory to create (must not exist); empty: runs/bags/<UTC time>")
    topics: list[str] = param(
        default_factory=default_record_topics,
        help="topics to record (relative names resolve in the node's namespace); types of topics "
        "outside the contract table (der_ros.contract) are discovered from the graph",
    )
    all_topics: bool = param(False, "also record every topic discovered in the graph (except exclude_topics)")
    record_scene: bool = param(
        True, "record the scene marker topics (scene/vehicles, scene/road) when they are in topics; false leaves "
        "them out (about 6 kB per ring step, 50 kB per urban step), and der bag render then has nothing to draw")
    exclude_topics: list[str] = param(
        default_factory=lambda: ["/rosout", "/parameter_events"],
        help="absolute topic names never recorded with all_topics",
    )
    discovery_period: float = param(
        1.0, "seconds between graph scans for new topics / publishers", low=0.05, high=60.0
    )
    queue_depth: int = param(
        1000, "history depth of the recorder's subscriptions (KEEP_LAST), large so bursts are not dropped",
        low=1, high=100000,
    )
    flush_every_messages: int = param(
        200, "flush the bag (finish the MCAP chunk, rewrite metadata.yaml) after this many messages; "
        "bounds what a SIGKILL loses", low=1, high=1_000_000,
    )
    flush_every_seconds: float = param(
        1.0, "... or after this many seconds of wall time with unflushed messages", low=0.01, high=3600.0
    )
    compression: str = param("none", "MCAP chunk compression", choices=("none", "zstd", "lz4"))
    max_bag_messages: int = param(0, "start a new .mcap file after this many messages (0: never split)", low=0)
    max_bag_size: int = param(0, "start a new .mcap file after about this many bytes (0: never split)", low=0)

    def check(self) -> None:
        if not self.topics and not self.all_topics:
            raise ConfigError("topics = [] with all_topics = false records nothing; give topics or set all_topics")
