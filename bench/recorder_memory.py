"""Does the recorder keep anything per message? tracemalloc over a recorder node fed in process (issue 45).

Runs ``RecorderNode`` and a publisher node in this process (one executor, a reserved ROS domain,
discovery on localhost), publishes ``--messages`` pairs of ``ego/odom`` (each also written to
``/tf`` by the recorder) and ``chatter`` (100 characters) after 2,000 pairs of warm-up, and
reports what Python memory grew over them, largest first (tracemalloc, 8 frames), with the RSS
growth per 1,000 pairs (tracemalloc's own traces included, so an upper bound). A container kept
forever shows as a growing entry with a count proportional to the messages.

``--graph``: what a ``der graph`` run publishes instead, step by step, with the recorder's graph
parameters (``config/graph.params.yaml``: every topic of its ``topics``): per decision step
``/clock``, ``reward`` (applied action, episode ends), ``state``, ``ego/odom``, ``lane_change_cmd``,
``safety/interventions`` and ``scene/vehicles`` (25 ring vehicles, new SUMO ids every episode);
an episode of ``--episode-steps`` steps (end + start events on ``episode``, ``agent/metrics`` at
each end), ``bridge/diagnostics`` every 200 steps, ``scene/road`` once; all made with the
contract's encoders, so each step's bytes are new. ``--messages`` is then decision steps
(warm-up 2,000 steps). The top growths are shown twice: all, and those whose traceback passes
through the recorder or the bag writer.

    .venv/bin/python bench/recorder_memory.py [--messages 4000] [--top 5]
    .venv/bin/python bench/recorder_memory.py --graph --messages 6000 [--episode-steps 5]
    .venv/bin/python bench/recorder_memory.py --graph --process --messages 20000 [--rate 100]

``--process`` (with ``--graph``): the recorder runs as the graph runs it, in a process of its own
(``python -m der_ros.nodes.recorder_node`` with the graph's params file), fed at ``--rate`` decision
steps per second; its VmRSS is sampled every 500 steps after the warm-up and the growth is the
least-squares slope, kB per 1,000 steps (what ``soak.py`` reports, without the rest of the graph).
The recorder's environment is this one's (e.g. ``MALLOC_ARENA_MAX=2``).
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
from typing import Any


def rss_kb() -> int:
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


class GraphTraffic:
    """Publishes, one decision step at a time, what a ``der graph`` run (ring, --safety) publishes."""

    def __init__(self, node: Any, episode_steps: int) -> None:
        import numpy as np

        from der_ros.contract import (
            BRIDGE_DIAGNOSTICS,
            CLOCK,
            COMMAND,
            EPISODE,
            METRICS,
            ODOM,
            REWARD,
            SAFETY_EVENTS,
            SCENE_ROAD,
            SCENE_VEHICLES,
            STATE,
            LaneLine,
        )
        from der_ros.contract_ros import message_class, topic_qos
        from sumo_bridge.observation import POINT_FIELDS

        self.np, self.fields, self.episode_steps = np, POINT_FIELDS, max(2, episode_steps)
        names = (
            CLOCK,
            REWARD,
            STATE,
            ODOM,
            COMMAND,
            SAFETY_EVENTS,
            SCENE_VEHICLES,
            EPISODE,
            METRICS,
            BRIDGE_DIAGNOSTICS,
            SCENE_ROAD,
        )
        from der_ros.contract import topic_spec

        self.pubs = {n: node.create_publisher(message_class(topic_spec(n).msgtype), n, topic_qos(n)) for n in names}
        self.names = dict(
            clock=CLOCK,
            reward=REWARD,
            state=STATE,
            odom=ODOM,
            cmd=COMMAND,
            safety=SAFETY_EVENTS,
            vehicles=SCENE_VEHICLES,
            episode=EPISODE,
            metrics=METRICS,
            diag=BRIDGE_DIAGNOSTICS,
        )
        from der_ros.contract import road_markers_cdr

        lanes = [LaneLine(f"ring_{i}", np.array([[0.0, 3.2 * i], [100.0, 3.2 * i]]), 3.2) for i in range(3)]
        self.pubs[SCENE_ROAD].publish(road_markers_cdr(lanes, 0))
        self.step_index, self.episode, self.vehicle_base = 0, 0, 0

    def subscribed(self) -> bool:
        return all(p.get_subscription_count() >= 1 for p in self.pubs.values())

    def step(self) -> int:
        """Publish one decision step; returns the messages published."""
        from der_ros.contract import (
            EGO_ROLE,
            EPISODE_START,
            EPISODE_TIME_LIMIT,
            TRAFFIC_ROLE,
            VehicleMarker,
            clock_cdr,
            command_cdr,
            episode_values,
            odometry_cdr,
            reward_cdr,
            state_cdr,
            vehicle_markers_cdr,
        )
        from der_ros.nodes.msg_conversions import (
            make_diagnostics,
            make_episode_event,
            make_safety_record,
            metrics_to_diagnostics,
        )

        np, k = self.np, self.step_index
        stamp = (k + 1) * 100_000_000
        in_episode = k % self.episode_steps
        end = in_episode == self.episode_steps - 1
        pub, n = self.pubs, self.names
        sent = 0
        if in_episode == 0:
            self.episode += 1
            self.vehicle_base += 25  # SUMO ids of a rebuilt ring are new names
            pub[n["episode"]].publish(make_episode_event(stamp, EPISODE_START, episode_values(self.episode, 0, None)))
            sent += 1
        pub[n["clock"]].publish(clock_cdr(stamp))
        pub[n["reward"]].publish(reward_cdr(stamp, 0.1 * (k % 7), False, end, None if in_episode == 0 else k % 3))
        points = np.random.default_rng(k).normal(size=(7, len(self.fields)))
        pub[n["state"]].publish(state_cdr(points, stamp, fields=self.fields))
        pub[n["odom"]].publish(odometry_cdr(stamp, float(k % 500), 3.2, 90.0, 25.0))
        pub[n["cmd"]].publish(command_cdr(stamp, k % 3, "agent_node"))
        pub[n["safety"]].publish(make_safety_record(stamp, "pass", k % 3, k % 3, k // 50))
        vehicles = [
            VehicleMarker(
                i, f"veh{self.vehicle_base + i}", EGO_ROLE if i == 0 else TRAFFIC_ROLE, 4.0 * i, 3.2, 0.01 * k, 5.0, 1.8
            )
            for i in range(25)
        ]
        pub[n["vehicles"]].publish(vehicle_markers_cdr(vehicles, [], stamp))
        sent += 7
        if end:
            values = episode_values(self.episode, self.episode_steps, 1.5, 1, 24.0, imposed_brake=0.0)
            pub[n["episode"]].publish(make_episode_event(stamp, EPISODE_TIME_LIMIT, values))
            pub[n["metrics"]].publish(
                metrics_to_diagnostics({"charts/episodic_return": 1.5, "losses/td_loss": 0.01 * k}, stamp)
            )
            sent += 2
        if k % 200 == 199:
            pub[n["diag"]].publish(make_diagnostics(stamp, "bridge", {"sim_steps": k, "steps_per_s": 90.0}))
            sent += 1
        self.step_index += 1
        return sent


def run_recorder_process(args: argparse.Namespace) -> int:
    """``--process``: the recorder node in its own process, graph traffic from this one (docstring)."""
    import json
    import signal
    import subprocess

    import rclpy
    import yaml

    repo = Path(__file__).resolve().parents[1]
    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "der_ros.nodes.recorder_node",
            "--ros-args",
            "--params-file",
            str(repo / "config/graph.params.yaml"),
            "-p",
            f"output:={tmp}/bag",
        ]
        child = subprocess.Popen(cmd, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        pub_node = rclpy.create_node("recorder_memory_publisher")
        traffic = GraphTraffic(pub_node, args.episode_steps)
        deadline = time.monotonic() + 60
        while not traffic.subscribed():
            time.sleep(0.1)
            if time.monotonic() > deadline or child.poll() is not None:
                print("the recorder did not subscribe within 60 s", file=sys.stderr)
                child.kill()
                return 1
        period, samples, published = 1.0 / args.rate, [], 0
        t_next = time.monotonic()
        for k in range(2000 + args.messages):
            published += traffic.step()
            if k >= 2000 and (k - 2000) % 500 == 0:
                kb = proc_rss_kb(child.pid)
                samples.append((k - 2000, kb))
            t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        time.sleep(2.0)
        samples.append((args.messages, proc_rss_kb(child.pid)))
        child.send_signal(signal.SIGINT)
        child.wait(timeout=60)
        meta = yaml.safe_load((Path(tmp) / "bag/metadata.yaml").read_text())["rosbag2_bagfile_information"]
        recorded = sum(
            t["message_count"] for t in meta["topics_with_message_count"] if t["topic_metadata"]["name"] != "/tf"
        )
    pub_node.destroy_node()
    rclpy.try_shutdown()
    slope = slope_per_1000(samples)
    env = {k: v for k, v in os.environ.items() if k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    print(f"recorder process: recorded {recorded} messages of {published} published (+ /tf); {len(samples)} RSS "
          f"samples over {args.messages} steps after 2,000 of warm-up, {samples[0][1] / 1024:.1f} -> "
          f"{samples[-1][1] / 1024:.1f} MB: {slope:+.1f} kB per 1,000 steps {env or ''}")  # fmt: skip
    print(
        json.dumps(
            {
                "bench": "recorder_memory",
                "process": True,
                "steps": args.messages,
                "rate": args.rate,
                "episode_steps": args.episode_steps,
                "env": env,
                "recorded": recorded,
                "published": published,
                "rss_first_mb": round(samples[0][1] / 1024, 1),
                "rss_last_mb": round(samples[-1][1] / 1024, 1),
                "kb_per_1000_steps": round(slope, 1),
            }
        )
    )
    return 0


def proc_rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for {pid}")


def slope_per_1000(points: list[tuple[int, int]]) -> float:
    """Least-squares slope of (step, kB) points, kB per 1,000 steps."""
    n = len(points)
    mx, my = sum(p[0] for p in points) / n, sum(p[1] for p in points) / n
    sxx = sum((p[0] - mx) ** 2 for p in points)
    return 1000.0 * sum((p[0] - mx) * (p[1] - my) for p in points) / sxx


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--messages",
        type=int,
        default=4000,
        help="odom + chatter pairs measured (default 4000); decision steps with --graph",
    )
    ap.add_argument("--top", type=int, default=5, help="largest growths shown (default 5)")
    ap.add_argument("--graph", action="store_true", help="publish what a der graph run publishes (docstring)")
    ap.add_argument("--episode-steps", type=int, default=5, help="--graph: decision steps per episode (default 5)")
    ap.add_argument("--process", action="store_true", help="--graph: the recorder in its own process (docstring)")
    ap.add_argument("--rate", type=float, default=100.0, help="--process: decision steps per second (default 100)")
    args = ap.parse_args()
    if args.process and not args.graph:
        ap.error("--process needs --graph")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from der_ros.graph.supervisor import reserve_domain_id

    lease = reserve_domain_id()
    os.environ["ROS_DOMAIN_ID"] = str(lease.domain_id)
    if args.process:
        try:
            return run_recorder_process(args)
        finally:
            lease.release()
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from der_ros.nodes.recorder_node import RecorderNode

    rclpy.init()
    with tempfile.TemporaryDirectory() as tmp:
        if args.graph:
            import yaml

            graph_params = yaml.safe_load(
                (Path(__file__).resolve().parents[1] / "config/graph.params.yaml").read_text()
            )
            rec_params = dict(graph_params["recorder_node"]["ros__parameters"], output=f"{tmp}/bag")
            rec = RecorderNode(parameter_overrides=[Parameter(k, value=v) for k, v in rec_params.items()
                                                    if k != "use_sim_time"])  # fmt: skip
        else:
            rec = RecorderNode(parameter_overrides=[Parameter("output", value=f"{tmp}/bag"),
                                                    Parameter("topics", value=["ego/odom", "chatter"])])  # fmt: skip
        pub_node = rclpy.create_node("recorder_memory_publisher")
        executor = SingleThreadedExecutor()
        executor.add_node(rec)
        executor.add_node(pub_node)
        if args.graph:
            traffic = GraphTraffic(pub_node, args.episode_steps)
            ready = traffic.subscribed
        else:
            odom = pub_node.create_publisher(Odometry, "ego/odom", 10)
            chatter = pub_node.create_publisher(String, "chatter", 10)

            def ready() -> bool:
                return odom.get_subscription_count() >= 1 and chatter.get_subscription_count() >= 1

        deadline = time.monotonic() + 60
        while not ready():
            executor.spin_once(timeout_sec=0.1)
            if time.monotonic() > deadline:
                print("the recorder did not subscribe within 60 s", file=sys.stderr)
                return 1
        published = 0

        def run(n: int) -> None:
            nonlocal published
            for i in range(n):
                if args.graph:
                    sent = traffic.step()
                else:
                    m = Odometry()
                    m.header.stamp.sec = i
                    m.header.frame_id, m.child_frame_id = "map", "ego"
                    m.pose.pose.position.x = float(i)
                    odom.publish(m)
                    chatter.publish(String(data="x" * 100))
                    sent = 2
                published += sent
                executor.spin_once(timeout_sec=0.05)
                for _ in range(sent + 1):
                    executor.spin_once(timeout_sec=0.0)

        run(2000)
        tracemalloc.start(8)
        received, sent0, rss0, snap0 = rec._received, published, rss_kb(), tracemalloc.take_snapshot()
        run(args.messages)
        snap1, rss1 = tracemalloc.take_snapshot(), rss_kb()
        tracemalloc.stop()
        unit = "steps" if args.graph else "pairs"
        print(f"recorded {rec._received - received} messages of {published - sent0} published (+ /tf) over "
              f"{args.messages} {unit}; RSS {1000 * (rss1 - rss0) / args.messages:+.1f} kB per 1,000 {unit} "
              "(this process: publisher and recorder; tracemalloc's traces included)")  # fmt: skip
        stats = snap1.compare_to(snap0, "traceback")
        ours = ("recorder_node.py", "writer.py", "chunk_index_spill.py")
        mine = [s for s in stats if any(Path(f.filename).name in ours for f in s.traceback)]
        for title, rows in (("largest Python growths", stats), ("... through the recorder / bag writer", mine)):
            total = sum(s.size_diff for s in rows)
            print(f"{title} (total {total:+d} B; bytes, blocks, innermost frames first):")
            for stat in rows[: args.top]:
                where = " < ".join(f"{Path(f.filename).name}:{f.lineno}" for f in list(stat.traceback)[::-1][:4])
                print(f"  {stat.size_diff:+9d} B {stat.count_diff:+6d}  {where}")
        rec.close()
        executor.shutdown()
    rclpy.try_shutdown()
    lease.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
