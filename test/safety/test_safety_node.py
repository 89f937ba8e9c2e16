"""safety_node in a real graph: it vetoes unsafe commands, fails safe, and a scripted "change now" agent
behind it causes no collision where the same agent without it does (docs/safety.md)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.qos import QoSProfile
from ros_harness import REPO, ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures
from sensor_msgs.msg import Joy, PointCloud2

from der_ros import contract as ct
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import empty_points, field_index

pytestmark = pytest.mark.ros

PARAMS_FILE = REPO / "config" / "graph.params.yaml"
COL = {n: field_index(n) for n in ("speed", "rel_speed", "gap", "lane", "target_lane", "present", "lane_count")}
LEFT_LEADER = 3


def state(left_leader_gap: float | None, speed: float = 10.0) -> np.ndarray:
    pts = empty_points()
    pts[0, COL["speed"]], pts[0, COL["lane"]], pts[0, COL["lane_count"]], pts[0, COL["target_lane"]] = speed, 0, 2, 1
    if left_leader_gap is not None:
        row = pts[LEFT_LEADER]
        row[COL["present"]], row[COL["gap"]], row[COL["rel_speed"]], row[COL["speed"]] = 1.0, left_leader_gap, 0.0, speed
        row[COL["lane"]] = 1
    return pts


def test_safety_node_vetoes_and_fails_safe(ros_graph) -> None:  # noqa: F811
    node = ros_graph.start_node("der_ros.nodes.safety_node", params_file=PARAMS_FILE, params={"max_state_age": 0.5})
    probe = ros_graph.probe
    out = probe.collect(ct.COMMAND, Joy)
    records = probe.collect(ct.SAFETY_EVENTS, DiagnosticArray)
    pub_state = probe.publisher(ct.STATE, PointCloud2, QoSProfile(depth=50))
    pub_cmd = probe.publisher(ct.AGENT_COMMAND, Joy)
    wait_for(lambda: pub_state.get_subscription_count() > 0 and pub_cmd.get_subscription_count() > 0, 60,
             what="the safety node's subscriptions", procs=[node])  # fmt: skip
    wait_for(lambda: "safety ready" in node.output(), 30, what="safety ready", procs=[node])

    def ask(stamp: int, action: int, points: np.ndarray | None, delay: float = 0.0) -> tuple[int, str]:
        n = len(out)
        if points is not None:
            pub_state.publish(mc.points_to_cloud(points, stamp))
            time.sleep(0.1 + delay)
        pub_cmd.publish(mc.make_command(stamp, action, "scripted-agent"))
        wait_for(lambda: len(out) > n and len(records) > n, 10, what=f"the answer to {stamp}", procs=[node])
        cmd, rec = out[n], ct.parse_safety_record(records[n])
        assert ct.header_ns(cmd) == stamp and rec is not None and rec[0] == stamp
        return int(cmd.buttons[0]), rec[1]

    assert ask(10**9, 1, state(None)) == (1, "pass")  # a free target lane: the change goes through
    assert ask(2 * 10**9, 1, state(28.0)) == (1, "pass")  # a leader far ahead at the same speed
    assert ask(3 * 10**9, 1, state(1.0)) == (0, "unsafe")  # a leader 1 m ahead: keep lane
    assert ask(4 * 10**9, 1, None) == (0, "no_state")  # a command for a state never seen
    bad = state(None)
    bad[0, COL["speed"]] = math.nan
    assert ask(5 * 10**9, 1, bad) == (0, "malformed")  # a NaN in the state
    assert ask(6 * 10**9, 1, state(None), delay=0.8) == (0, "stale")  # the state is older than max_state_age
    assert ask(7 * 10**9, 0, None) == (0, "pass")  # keep lane needs no state
    assert ct.parse_safety_record(records[-1])[4] == 4  # four interventions so far


def _run(ros_graph, steps: int, shielded: bool, seed: int) -> tuple[int, int, int]:  # noqa: F811
    """A bridge on the ring and a scripted agent that always commands "left" (the target lane is the left
    one) the moment a state arrives. Returns (episodes, caused collisions, interventions)."""
    probe = ros_graph.probe
    topic = ct.AGENT_COMMAND if shielded else ct.COMMAND
    pub = probe.publisher(topic, Joy)
    probe.node.create_subscription(PointCloud2, ct.STATE, lambda m: pub.publish(
        mc.make_command(ct.header_ns(m), 1, "always-change-now")), QoSProfile(depth=50))  # fmt: skip
    rewards = probe.collect(ct.REWARD, Vector3Stamped, QoSProfile(depth=1000))
    records = probe.collect(ct.SAFETY_EVENTS, DiagnosticArray, QoSProfile(depth=1000))
    procs = []
    if shielded:
        procs.append(ros_graph.start_node("der_ros.nodes.safety_node", params_file=PARAMS_FILE))
        wait_for(lambda: "safety ready" in procs[0].output(), 60, what="safety ready", procs=procs)
    bridge = ros_graph.start_node("der_ros.nodes.bridge_node", params_file=PARAMS_FILE,
                                  params={"max_steps": steps, "markers": False, "scenario.seed": seed,
                                          "wait_for_agent": 120.0, "command_timeout": 5.0})  # fmt: skip
    assert bridge.wait(timeout=600) == 0, bridge.output()[-3000:]
    time.sleep(0.5)
    ends = [r for r in rewards if r.vector.y > 0.5 or r.vector.z > 0.5]
    caused = sum(r.vector.x < -50.0 for r in ends)  # the -100 of a caused collision (section 5.1)
    interventions = ct.parse_safety_record(records[-1])[4] if records else 0
    return len(ends), caused, interventions


@pytest.mark.parametrize("shielded", [False, True], ids=["unshielded", "behind-safety-node"])
def test_change_now_agent_behind_the_safety_node_causes_no_collision(ros_graph, shielded: bool) -> None:  # noqa: F811
    episodes, caused, interventions = _run(ros_graph, steps=400, shielded=shielded, seed=3)
    print(f"shielded={shielded}: {episodes} episodes, {caused} caused collisions, {interventions} interventions")
    assert episodes >= 8
    if shielded:
        assert caused == 0 and interventions > 0
    else:
        assert caused > 0 and interventions == 0
