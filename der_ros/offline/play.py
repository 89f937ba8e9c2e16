"""``der bag play``: publish a bag's messages back into a ROS 2 graph, like ``ros2 bag play``.

* Raw CDR bytes are published as recorded (rclpy's ``Publisher.publish`` accepts ``bytes``
  and hands them to ``publish_raw``), so nothing is deserialised on the way.
* Each topic is offered the QoS it was recorded with (``offered_qos_profiles``, merged by
  :func:`der_ros.contract.merged_qos`); the depth falls back to the topic table's.
* Timing: message i goes out at ``t0 + (log_time_i - log_time_0) / rate`` (wall clock,
  ``time.perf_counter``), so inter-message gaps are the recorded ones scaled by ``--rate``.
* ``/clock`` is republished like any topic when recorded; ``--clock`` synthesises it from the
  log times when the bag has none.
* What it cannot play is an error, not "published 0 messages": a der_ros topic name recorded
  with another type (another graph's ``/clock`` as ``std_msgs/String``), or a bag with nothing
  publishable (a JSON MCAP, types not installed, ``--topics`` not in the bag).

The one module of the bag package that needs rclpy (imported at the top: ``der bag`` loads
it only when ``play`` runs).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from rclpy.executors import ExternalShutdownException
from rosgraph_msgs.msg import Clock

from der_ros.bag.reader import BagError, BagReader, Connection, Message
from der_ros.contract import CLOCK, merged_qos, topic_by_name, topic_spec
from der_ros.contract_ros import message_class, qos_profile
from der_ros.offline.episodes import mistyped_topics

__all__ = ["run_play", "play_bag"]

log = logging.getLogger(__name__)


def play_bag(node: Any, reader: BagReader, *, rate: float = 1.0, loop: bool = False,
             topics: list[str] | None = None, clock: bool = False, wait_subscribers: float = 0.0,
             delay: float = 0.0, max_loops: int | None = None,
             now: Callable[[], float] = time.perf_counter, sleep: Callable[[float], None] = time.sleep) -> int:
    """Publish the bag through ``node``'s publishers; returns the number of messages published.

    With ``loop`` the bag starts again at its end (``max_loops`` passes at most, None = forever).
    ``now`` and ``sleep`` are the clock the schedule runs on (a test passes a simulated one, so
    the schedule is checked exactly and without wall-clock thresholds).
    """
    if not rate > 0:
        raise ValueError(f"rate = {rate!r}, expected > 0")
    conns: dict[str, list[Connection]] = {}
    for c in reader.connections():
        if topics is None or c.topic in topics:
            conns.setdefault(c.topic, []).append(c)
    if topics is not None:
        for t in set(topics) - set(conns):
            log.warning("topic %s is not in the bag", t)
    wrong = [w for t, w in mistyped_topics(reader).items() if t in conns]
    if wrong:  # subscribers of our topics would get another type (or nothing: a type mismatch never matches)
        raise BagError(reader.path, None, f"{'; '.join(wrong)}: not a der_ros graph's bag on these topics; pick "
                       "other topics with --topics")
    pubs: dict[str, Any] = {}
    skipped: list[str] = []
    for topic, cs in conns.items():
        if cs[0].message_encoding != "cdr":
            skipped.append(f"{topic} is {cs[0].message_encoding}-encoded, not ROS 2 CDR")
            log.warning("skipping %s", skipped[-1])
            continue
        cls = message_class(cs[0].msgtype)
        if cls is None:
            skipped.append(f"{topic}: message type {cs[0].msgtype} is not installed")
            log.warning("skipping %s", skipped[-1])
            continue
        profiles = tuple(p for c in cs for p in c.offered_qos)
        spec = topic_by_name(topic)
        q = merged_qos(profiles, spec.qos.depth if spec is not None and spec.msgtype == cs[0].msgtype else 10)
        pubs[topic] = node.create_publisher(cls, topic, qos_profile(q))
        log.info("publishing %s (%s) with %s", topic, cs[0].msgtype, q)
    if not pubs:
        why = "; ".join(skipped) if skipped else ("none of --topics is in the bag" if topics is not None
                                                   else "the bag holds no topic")
        raise BagError(reader.path, None, f"nothing to play: {why}")
    clock_pub = None
    if clock and CLOCK not in pubs:
        clock_pub = node.create_publisher(Clock, CLOCK, qos_profile(topic_spec(CLOCK).qos))
        pubs_for_wait = [*pubs.values(), clock_pub]
    else:
        pubs_for_wait = list(pubs.values())
    if wait_subscribers > 0 and pubs_for_wait:
        deadline = time.monotonic() + wait_subscribers
        while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in pubs_for_wait):
            time.sleep(0.02)
        missing = [p.topic_name for p in pubs_for_wait if p.get_subscription_count() == 0]
        if missing:
            log.warning("no subscriber after %.1f s on %s; playing anyway", wait_subscribers, ", ".join(missing))
    if delay > 0:
        time.sleep(delay)
    wanted = set(pubs)
    published = 0
    passes = 0
    while True:
        passes += 1
        t0: float | None = None
        first: int | None = None
        for msg in reader.messages(wanted):
            if first is None:
                first = msg.log_time
            due = max(0, msg.log_time - first) / 1e9 / rate
            t = now()
            if t0 is None:
                t0 = t
            wait = t0 + due - t
            if wait > 0:
                sleep(wait)
            if clock_pub is not None:
                _publish_clock(clock_pub, msg)
            pubs[msg.topic].publish(bytes(msg.data))
            published += 1
        if not loop or first is None or (max_loops is not None and passes >= max_loops):
            return published


def _publish_clock(pub: Any, msg: Message) -> None:
    sec, nsec = divmod(msg.log_time, 1_000_000_000)
    pub.publish(Clock(clock=Time(sec=sec, nanosec=nsec)))


def run_play(args: argparse.Namespace) -> int:
    if not args.rate > 0:
        print(f"der bag play: --rate {args.rate}: expected a number > 0")
        return 2
    reader = BagReader(args.bag)
    rclpy.init()
    node = rclpy.create_node("der_replay_player")
    try:
        n = play_bag(node, reader, rate=args.rate, loop=args.loop, topics=args.topics, clock=args.clock,
                     wait_subscribers=args.wait_subscribers, delay=args.delay)
        node.get_logger().info(f"published {n} messages from {args.bag}")
        time.sleep(0.2)  # let reliable writers deliver the tail before the node goes away
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0
