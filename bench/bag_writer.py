"""Bag write throughput: der_ros's BagWriter (recorder path) vs rosbags' rosbag2 Writer, same data.

The recorder hands CDR bytes to ``BagWriter.write``; this measures that path with the recorder's
default flush policy (every 200 messages / 1 s: finish the MCAP chunk, flush the file, rewrite
metadata.yaml) and with flushing effectively off, against ``rosbags.rosbag2.Writer`` (MCAP
storage, version 9, 1 MiB chunks, no periodic flush) writing the same bytes. Messages are the
graph's per-step mix: a ~1 KB ``state`` PointCloud2 and small ``reward``/``lane_change_cmd``/
``/clock`` messages, in turn. Best of ``--repeat`` runs. Ends with one JSON line:
ours_msgs_per_s (default flushing), ours_noflush_msgs_per_s, rosbags_msgs_per_s, ratio
(ours / rosbags), flush_cost (1 - ours / ours_noflush), messages.

    .venv/bin/python bench/bag_writer.py [--messages 200000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import gc
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

TOPICS = [
    ("/state", "sensor_msgs/msg/PointCloud2"),
    ("/reward", "geometry_msgs/msg/Vector3Stamped"),
    ("/lane_change_cmd", "sensor_msgs/msg/Joy"),
    ("/clock", "rosgraph_msgs/msg/Clock"),
]


def payloads() -> list[bytes]:
    """One CDR payload per topic (serialised once; the writers only move bytes, as the recorder does)."""
    from der_ros.bag.writer import jazzy_typestore

    store = jazzy_typestore()
    T = store.types
    stamp = T["builtin_interfaces/msg/Time"](sec=12, nanosec=500)
    head = T["std_msgs/msg/Header"](stamp=stamp, frame_id="ego")
    fields = [T["sensor_msgs/msg/PointField"](name=f"f{i}", offset=8 * i, datatype=8, count=1) for i in range(12)]
    cloud = T["sensor_msgs/msg/PointCloud2"](
        header=head, height=1, width=11, fields=fields, is_bigendian=False, point_step=96, row_step=96 * 11,
        data=np.arange(96 * 11, dtype=np.uint8), is_dense=True,
    )
    reward = T["geometry_msgs/msg/Vector3Stamped"](header=head, vector=T["geometry_msgs/msg/Vector3"](x=1.0, y=0.0, z=0.0))
    joy = T["sensor_msgs/msg/Joy"](header=head, axes=np.zeros(0, dtype=np.float32), buttons=np.array([1], dtype=np.int32))
    clock = T["rosgraph_msgs/msg/Clock"](clock=stamp)
    return [bytes(store.serialize_cdr(m, t)) for m, (_n, t) in zip((cloud, reward, joy, clock), TOPICS)]


def write_ours(path: Path, n: int, data: list[bytes], flush: bool) -> None:
    from der_ros.bag.writer import BagWriter

    kw = {} if flush else {"flush_every_messages": 10**9, "flush_every_seconds": 1e9}
    w = BagWriter(path, **kw)
    for name, msgtype in TOPICS:
        w.add_topic(name, msgtype)
    names = [t[0] for t in TOPICS]
    for i in range(n):
        k = i % 4
        w.write(names[k], 1_000 + i, data[k])
    w.close()


def write_rosbags(path: Path, n: int, data: list[bytes]) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    from der_ros.bag.writer import jazzy_typestore

    store = jazzy_typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = [w.add_connection(name, msgtype, typestore=store) for name, msgtype in TOPICS]
        for i in range(n):
            k = i % 4
            w.write(conns[k], 1_000 + i, data[k])


def best_of(fn, n: int, repeat: int) -> float:  # noqa: ANN001
    best = float("inf")
    root = Path(tempfile.mkdtemp(prefix="der_bench_writer_"))
    try:
        for r in range(repeat):
            gc.collect()
            path = root / f"bag{r}"
            t0 = time.perf_counter()
            fn(path)
            best = min(best, time.perf_counter() - t0)
            shutil.rmtree(path)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return n / best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=200_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    data = payloads()
    n = args.messages
    ours = best_of(lambda p: write_ours(p, n, data, flush=True), n, args.repeat)
    ours_noflush = best_of(lambda p: write_ours(p, n, data, flush=False), n, args.repeat)
    peer = best_of(lambda p: write_rosbags(p, n, data), n, args.repeat)
    print(json.dumps({
        "ours_msgs_per_s": round(ours),
        "ours_noflush_msgs_per_s": round(ours_noflush),
        "rosbags_msgs_per_s": round(peer),
        "ratio": round(ours / peer, 3),
        "flush_cost": round(1.0 - ours / ours_noflush, 3),
        "messages": n,
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
