"""Node tests of agent_node: a real agent process, the test's probe node plays the bridge."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.qos import QoSProfile
from ros_harness import ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures
from sensor_msgs.msg import Joy, PointCloud2, PointField
from std_srvs.srv import SetBool, Trigger

from der_ros import contract as ct
from der_ros.agent.config import DQNConfig
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import empty_points, field_index

pytestmark = pytest.mark.ros

STEP_NS = 500_000_000
EPISODE = 8  # steps per synthetic episode (the last one terminal)
RELIABLE_50 = QoSProfile(depth=50)

AGENT_PARAMS = {
    "agent.learning_starts": 8,
    "agent.batch_size": 8,
    "agent.hidden_sizes": [32],
    "agent.epsilon_decay_steps": 20,
    "replay.capacity": 1000,
    "replay.lam": 0.5,
    "metrics_every": 1,
    "step_seconds": STEP_NS / 1e9,
}


class FakeBridge:
    """Publishes synthetic reward/state pairs and collects the agent's answers."""

    def __init__(self, graph, params):
        self.probe = graph.probe
        self.pub_state = self.probe.publisher("state", PointCloud2, RELIABLE_50)
        self.pub_reward = self.probe.publisher("reward", Vector3Stamped, RELIABLE_50)
        self.cmds = self.probe.collect("lane_change_cmd", Joy)
        self.metrics = self.probe.collect("agent/metrics", DiagnosticArray)
        self.rng = np.random.default_rng(0)
        self.k = 0
        self.proc = graph.start_node("der_ros.nodes.agent_node", params=params)
        node = self.probe.node
        wait_for(
            lambda: node.count_subscribers("state") and node.count_subscribers("reward")
            and node.count_publishers("lane_change_cmd"),
            30, what="agent to join the graph", procs=[self.proc],
        )
        wait_for(  # our writers matched the agent's readers (count_subscribers above is only the graph's view)
            lambda: self.pub_state.get_subscription_count() > 0 and self.pub_reward.get_subscription_count() > 0,
            30, what="our state/reward writers to match the agent's readers", procs=[self.proc])
        # and it finished setting up (torch, warm-up): on a loaded machine that took longer than one answer's wait
        wait_for(lambda: "agent ready" in self.proc.output(), 120, what="agent ready", procs=[self.proc])

    def points(self) -> np.ndarray:
        pts = empty_points()
        pts[0, field_index("speed")] = self.rng.uniform(0, 15)
        pts[0, field_index("lane_count")] = 2
        pts[1:, field_index("present")] = self.rng.integers(0, 2, size=len(pts) - 1)
        pts[1:, field_index("gap")] = self.rng.uniform(-5, 30, size=len(pts) - 1)
        return pts

    def step(self, terminal: bool = False, first: bool = False) -> int:
        """Publish step k (reward before state); returns its stamp."""
        stamp = self.k * STEP_NS
        reward = 0.0 if first else float(self.rng.normal())
        self.pub_reward.publish(mc.make_reward(stamp, reward, terminal, False))
        self.pub_state.publish(mc.points_to_cloud(self.points(), stamp))
        self.k += 1
        return stamp

    def answer(self, stamp: int, timeout: float = 20.0) -> Joy:
        return wait_for(
            lambda: next((c for c in list(self.cmds) if ct.stamp_to_ns(c.header.stamp) == stamp), None),
            timeout, what=f"command for {stamp}", procs=[self.proc],
        )

    def run_episode(self) -> list[Joy]:
        """One synthetic episode, answering like a lockstep bridge waits for the command."""
        out = []
        for i in range(EPISODE):
            stamp = self.step(terminal=i == EPISODE - 1, first=i == 0)
            if i < EPISODE - 1:
                out.append(self.answer(stamp))
        return out

    def latest_metrics(self, pred, what: str, timeout: float = 20.0) -> dict[str, float]:
        def find():
            for m in reversed(list(self.metrics)):
                values = ct.diagnostics_to_metrics(m)
                if pred(values):
                    return values
            return None

        return wait_for(find, timeout, what=what, procs=[self.proc])


def test_agent_answers_every_state_learns_and_fills_h2(ros_graph, tmp_path):  # noqa: F811
    ckpt = tmp_path / "agent.pt"
    b = FakeBridge(ros_graph, {**AGENT_PARAMS, "checkpoint_out": str(ckpt)})
    cmds = []
    for _ in range(5):
        cmds += b.run_episode()
    assert len(cmds) == 5 * (EPISODE - 1)
    senders = {c.header.frame_id for c in cmds}
    assert len(senders) == 1 and "agent_node" in senders.pop()
    assert all(len(c.buttons) == 1 and 0 <= c.buttons[0] < 3 for c in cmds)
    # terminal states get no command
    terminal_stamps = {(e * EPISODE + EPISODE - 1) * STEP_NS for e in range(5)}
    assert not terminal_stamps & {ct.stamp_to_ns(c.header.stamp) for c in b.cmds}
    m = b.latest_metrics(lambda v: v.get("replay/h2_size", 0) > 0, "H2 to receive promoted transitions")
    assert "losses/td_loss" in m and np.isfinite(m["losses/td_loss"])
    assert b.latest_metrics(lambda v: "charts/episodic_return" in v, "an episodic return")["charts/episodes"] >= 1
    final = b.latest_metrics(lambda v: v.get("online/transitions", 0) >= 5 * (EPISODE - 1), "all transitions")
    assert final["online/gaps"] == 0 and final["online/duplicate_state"] == 0

    # evaluation mode: still answers, stores nothing
    res = b.probe.call(SetBool, "/agent/set_paused", SetBool.Request(data=True))
    assert res.success
    before = final["online/transitions"]
    cmds = b.run_episode()
    assert len(cmds) == EPISODE - 1
    paused = b.latest_metrics(lambda v: v.get("eval/episodes", 0) >= 1, "an evaluation episode")
    assert paused["online/transitions"] == before and paused["online/paused"] == 1.0
    assert b.probe.call(SetBool, "/agent/set_paused", SetBool.Request(data=False)).success

    # checkpoint on request, then on SIGINT (exit 0), then a restart loads it
    res = b.probe.call(Trigger, "/agent/save_checkpoint", Trigger.Request())
    assert res.success and res.message == str(ckpt) and ckpt.is_file()
    assert b.proc.stop() == 0
    assert "stopping (SIGINT)" in b.proc.output() and b.proc.output().count(f"saved {ckpt}") == 2
    ckpt2 = tmp_path / "agent2.pt"
    again = ros_graph.start_node(
        "der_ros.nodes.agent_node",
        params={**AGENT_PARAMS, "checkpoint_in": str(ckpt), "checkpoint_out": str(ckpt2)},
        name="agent_node",
    )
    steps = int(before)
    wait_for(lambda: f"loaded {ckpt} (step {steps})" in again.output(), 30, what="checkpoint load", procs=[again])
    # SIGTERM is handled like SIGINT: final checkpoint, exit 0
    again.signal(signal.SIGTERM)
    assert again.wait(timeout=20) == 0
    assert "stopping (SIGTERM)" in again.output() and ckpt2.is_file()


def test_agent_rejects_bad_messages_and_parameters_without_a_crash(ros_graph):  # noqa: F811
    b = FakeBridge(ros_graph, AGENT_PARAMS)
    # one valid episode first: its answers show both sides of every topic matched, so nothing below is lost
    assert len(b.run_episode()) == EPISODE - 1
    # a state whose layout is not the contract's, and a reward with a NaN (at the next step's stamp)
    stamp = b.k * STEP_NS
    bad = mc.points_to_cloud(b.points(), stamp)
    bad.fields = bad.fields[:-1] + [PointField(name="bogus", offset=88, datatype=PointField.FLOAT64, count=1)]
    b.pub_state.publish(bad)
    nan_reward = mc.make_reward(stamp, 0.0, False, False)
    nan_reward.vector.x = float("nan")
    b.pub_reward.publish(nan_reward)
    # then a valid episode still works
    assert len(b.run_episode()) == EPISODE - 1
    m = b.latest_metrics(lambda v: v.get("agent/bad_state", 0) >= 1 and v.get("agent/bad_reward", 0) >= 1,
                         "bad-message counters")
    assert m["agent/bad_state"] == 1 and m["agent/bad_reward"] == 1

    # replay.lam = 1.5: refused with a reason, value unchanged
    (res,) = b.probe.set_parameters("agent_node", {"replay.lam": 1.5})
    assert not res.successful and "lam" in res.reason
    (res,) = b.probe.set_parameters("agent_node", {"agent.lr": -1.0})  # mutable, but out of range
    assert not res.successful and "agent.lr" in res.reason
    (res,) = b.probe.set_parameters("agent_node", {"replay.kind": "bogus"})
    assert not res.successful and res.reason
    assert b.probe.get_parameters("agent_node", ["replay.lam", "agent.lr", "replay.kind"]) == {
        "replay.lam": 0.5, "agent.lr": DQNConfig().lr, "replay.kind": "der"}
    # a valid runtime change is applied
    (res,) = b.probe.set_parameters("agent_node", {"replay.lam": 0.25})
    assert res.successful
    assert b.probe.get_parameters("agent_node", ["replay.lam"]) == {"replay.lam": 0.25}
    assert len(b.run_episode()) == EPISODE - 1
    assert b.proc.poll() is None


def test_agent_reports_ready_only_once_its_commands_have_a_subscriber(ros_graph):  # noqa: F811
    # der graph starts the recorder, then the agent, and waits for "agent ready" before the bridge: with
    # min_command_subscribers the line waits until the command writer is matched, so no command goes unrecorded
    probe = ros_graph.probe
    proc = ros_graph.start_node("der_ros.nodes.agent_node",
                                params={**AGENT_PARAMS, "warm_up": False, "min_command_subscribers": 1})
    wait_for(lambda: probe.node.count_publishers("lane_change_cmd"), 30, what="the agent's command publisher",
             procs=[proc])
    time.sleep(1.0)
    assert "agent ready" not in proc.output()
    probe.collect("lane_change_cmd", Joy)
    wait_for(lambda: "agent ready" in proc.output(), 20, what="agent ready after a subscriber", procs=[proc])
    assert "starting anyway" not in proc.output()

    # nobody subscribes: ready anyway after command_wait_timeout, with a warning that says why
    alone = ros_graph.start_node("der_ros.nodes.agent_node", name="agent_alone",
                                 params={**AGENT_PARAMS, "warm_up": False, "min_command_subscribers": 3,
                                         "command_wait_timeout": 1.0})
    wait_for(lambda: "agent ready" in alone.output(), 30, what="agent ready after the timeout", procs=[alone])
    out = alone.output()
    assert "expected min_command_subscribers = 3; starting anyway" in out
    assert out.index("starting anyway") < out.index("agent ready")
