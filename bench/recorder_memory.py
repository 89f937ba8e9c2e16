"""Does the recorder keep anything per message? tracemalloc over a recorder node fed in process (issue 45).

Runs ``RecorderNode`` and a publisher node in this process (one executor, a reserved ROS domain,
discovery on localhost), publishes ``--messages`` pairs of ``ego/odom`` (each also written to
``/tf`` by the recorder) and ``chatter`` (100 characters) after 2,000 pairs of warm-up, and
reports what Python memory grew over them, largest first (tracemalloc, 8 frames), with the RSS
growth per 1,000 pairs (tracemalloc's own traces included, so an upper bound). A container kept
forever shows as a growing entry with a count proportional to the messages.

    .venv/bin/python bench/recorder_memory.py [--messages 4000] [--top 5]
"""

from __future__ import annotations

import argparse
import ctypes
import os
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path


def rss_kb() -> int:
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--messages", type=int, default=4000, help="odom + chatter pairs measured (default 4000)")
    ap.add_argument("--top", type=int, default=5, help="largest growths shown (default 5)")
    args = ap.parse_args()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from der_ros.graph.supervisor import reserve_domain_id

    lease = reserve_domain_id()
    os.environ["ROS_DOMAIN_ID"] = str(lease.domain_id)
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from der_ros.nodes.recorder_node import RecorderNode

    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        rec = RecorderNode(parameter_overrides=[Parameter("output", value=f"{tmp}/bag"),
                                                Parameter("topics", value=["ego/odom", "chatter"])])  # fmt: skip
        pub_node = rclpy.create_node("recorder_memory_publisher")
        odom = pub_node.create_publisher(Odometry, "ego/odom", 10)
        chatter = pub_node.create_publisher(String, "chatter", 10)
        executor = SingleThreadedExecutor()
        executor.add_node(rec)
        executor.add_node(pub_node)
        deadline = time.monotonic() + 60
        while odom.get_subscription_count() < 1 or chatter.get_subscription_count() < 1:
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline:
                print("the recorder did not subscribe within 60 s", file=sys.stderr)
                return 1

        def run(n: int) -> None:
            for i in range(n):
                m = Odometry()
                m.header.stamp.sec = i
                m.header.frame_id, m.child_frame_id = "map", "ego"
                m.pose.pose.position.x = float(i)
                odom.publish(m)
                chatter.publish(String(data="x" * 100))
                executor.spin_once(timeout_sec=0.05)
                executor.spin_once(timeout_sec=0.0)
                executor.spin_once(timeout_sec=0.0)

        run(2000)
        tracemalloc.start(8)
        received, rss0, snap0 = rec._received, rss_kb(), tracemalloc.take_snapshot()
        run(args.messages)
        snap1, rss1 = tracemalloc.take_snapshot(), rss_kb()
        tracemalloc.stop()
        print(f"recorded {rec._received - received} messages of {2 * args.messages} published (+ /tf); "
              f"RSS {1000 * (rss1 - rss0) / args.messages:+.1f} kB per 1,000 pairs (tracemalloc's traces included)")  # fmt: skip
        print("largest Python growths (bytes, blocks, innermost frames first):")
        for stat in snap1.compare_to(snap0, "traceback")[: args.top]:
            where = " < ".join(f"{Path(f.filename).name}:{f.lineno}" for f in list(stat.traceback)[::-1][:4])
            print(f"  {stat.size_diff:+9d} B {stat.count_diff:+6d}  {where}")
        rec.close()
        executor.shutdown()
    rclpy.try_shutdown()
    lease.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
