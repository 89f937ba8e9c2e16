"""Node tests of bridge_node: a real bridge process, the test's probe node plays the agent."""

from __future__ import annotations

import math

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from ros_harness import ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Joy, PointCloud2

from der_ros import contract as ct
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import POINT_FIELDS, SLOT_NAMES, field_index
from sumo_bridge.scenario import ScenarioConfig

pytestmark = pytest.mark.ros

STEP_NS = int(round(ScenarioConfig().step_seconds * 1e9))
LANE = field_index("lane")
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


class FakeAgent:
    """The probe's view of the bridge: messages by stamp, and a command publisher."""

    def __init__(self, graph, **params):
        base = {"wait_for_agent": 20.0, "command_timeout": 10.0, "diagnostics_every": 1}
        base.update(params)
        self.probe = graph.probe
        self.states = self.probe.collect("state", PointCloud2)
        self.rewards = self.probe.collect("reward", Vector3Stamped)
        self.episodes = self.probe.collect("episode", DiagnosticArray)
        self.diags = self.probe.collect("bridge/diagnostics", DiagnosticArray)
        self.clocks = self.probe.collect("/clock", Clock, qos=BEST_EFFORT)
        self.odoms = self.probe.collect("ego/odom", Odometry, qos=qos_profile_sensor_data)
        self.cmd = self.probe.publisher("lane_change_cmd", Joy)
        self.proc = graph.start_node("der_ros.nodes.bridge_node", params=base)

    def state(self, k: int, timeout: float = 30.0) -> PointCloud2:
        stamp = k * STEP_NS

        def find():
            return next((m for m in list(self.states) if ct.stamp_to_ns(m.header.stamp) == stamp), None)

        return wait_for(find, timeout, what=f"state stamped {stamp}", procs=[self.proc])

    def lane(self, k: int) -> int:
        return int(ct.cloud_to_points(self.state(k))[0, LANE])

    def send(self, k: int, action: int, sender: str = "probe", buttons=None, axes=None) -> None:
        msg = mc.make_command(k * STEP_NS, action, sender)
        if buttons is not None:
            msg.buttons = buttons
        if axes is not None:
            msg.axes = axes
        self.cmd.publish(msg)

    def counters(self, at_least_steps: int = 0, timeout: float = 20.0) -> dict[str, float]:
        """Latest bridge/diagnostics values once the bridge did at least ``at_least_steps`` steps."""

        def latest():
            if not self.diags:
                return None
            values = ct.diagnostics_to_metrics(self.diags[-1])
            return values if values.get("sim_steps", 0) >= at_least_steps else None

        return wait_for(latest, timeout, what=f"bridge diagnostics after {at_least_steps} steps", procs=[self.proc])


def test_publishes_contract_layout_and_lane_change_moves_the_ego(ros_graph):  # noqa: F811
    a = FakeAgent(ros_graph)
    s0 = a.state(0)
    assert [f.name for f in s0.fields] == list(POINT_FIELDS)
    assert s0.width * s0.height == 1 + len(SLOT_NAMES)
    points = ct.cloud_to_points(s0)
    assert points[0, field_index("present")] == 1.0 and points[0, LANE] == 0  # ego starts on the outer lane
    r0 = wait_for(lambda: [m for m in a.rewards if ct.stamp_to_ns(m.header.stamp) == 0], 5, what="reward 0")[0]
    assert ct.parse_reward(r0) == (0, 0.0, False, False, None)
    starts = wait_for(lambda: [e for m in a.episodes for e in ct.parse_episode_events(m)], 5, what="episode start")
    assert starts[0][:2] == (0, "start")
    # keep lane for three steps: the ego stays on lane 0 and every state arrives at t_k = k * step
    for k in range(3):
        a.send(k, 0)
        assert a.lane(k + 1) == 0
    # change left (towards lane 1, the inner lane): visible in the very next state
    a.send(3, 1)
    assert a.lane(4) == 1
    r4 = wait_for(lambda: next((m for m in list(a.rewards) if ct.stamp_to_ns(m.header.stamp) == 4 * STEP_NS), None),
                  5, what="reward 4")
    assert math.isfinite(r4.vector.x) and ct.parse_applied_action(r4) == 1
    assert ct.parse_applied_action(r0) is None  # an episode's first state follows no action
    # /clock carries the same step keys (best effort: some may be dropped, never out of order)
    clocks = [ct.stamp_to_ns(c.clock) for c in list(a.clocks)]
    assert clocks and clocks == sorted(clocks) and set(clocks) <= {k * STEP_NS for k in range(10)}
    wait_for(lambda: any(ct.stamp_to_ns(o.header.stamp) == 4 * STEP_NS for o in list(a.odoms)), 5, what="ego/odom")
    c = a.counters(at_least_steps=4)
    assert c["commands/accepted"] == 4 and c["commands/timeouts"] == 0


def test_lockstep_late_command_and_duplicate_never_apply_to_another_step(ros_graph):  # noqa: F811
    timeout = 1.0
    a = FakeAgent(ros_graph, command_timeout=timeout)
    a.state(0)
    # no answer to step 0 within the timeout: the default (keep lane) is applied (step 1 comes after it)
    assert a.lane(1) == 0
    r1 = next(m for m in list(a.rewards) if ct.stamp_to_ns(m.header.stamp) == STEP_NS)
    assert ct.parse_applied_action(r1) == 0  # the reward says which action was really applied
    # the late answer to step 0 asks for a lane change; it must not be applied to step 1
    a.send(0, 1)
    a.send(1, 0)
    assert a.lane(2) == 0
    # a duplicate of the answer to step 2 (with another action) must not be applied to step 3
    a.send(2, 0)
    a.send(2, 1)
    a.state(3)
    a.send(3, 0)
    assert a.lane(4) == 0
    c = a.counters(at_least_steps=4)
    assert c["commands/late"] == 1
    assert c["commands/duplicate"] == 1
    assert c["commands/timeouts"] == 1
    assert c["commands/accepted"] == 3


def test_bad_commands_and_parameters_are_rejected_without_a_crash(ros_graph):  # noqa: F811
    a = FakeAgent(ros_graph)
    a.state(0)
    a.send(0, 5)  # out of range
    a.send(0, 0, buttons=[0, 1])  # wrong size
    a.send(0, 0, buttons=[])
    a.send(0, 0, axes=[float("nan")])  # NaN in axes
    a.send(7, 0)  # a step that was never published
    a.send(0, 0, sender="agent-A")  # the first valid command locks the sender
    assert a.lane(1) == 0
    # another commander asks for a lane change at the open step 1. The bridge screens by the sender id in the
    # message; sent on the same writer as agent-A's answer it arrives first for sure (one writer is ordered;
    # two are not, and a sleep is no synchronisation)
    a.send(1, 1, sender="intruder")
    a.send(1, 0, sender="agent-A")
    assert a.lane(2) == 0  # the intruder's lane change was not applied
    c = a.counters(at_least_steps=2)
    assert c["commands/out_of_range"] == 1
    assert c["commands/malformed"] == 3
    assert c["commands/unknown_step"] == 1
    assert c["commands/foreign_sender"] == 1
    assert c["commands/accepted"] == 2 and c["commands/timeouts"] == 0

    # parameters: read-only and invalid values are refused with a reason; nothing changes
    results = a.probe.set_parameters("bridge_node", {"command_timeout": -1.0})
    assert not results[0].successful and results[0].reason
    results = a.probe.set_parameters("bridge_node", {"mode": "bogus"})
    assert not results[0].successful and results[0].reason
    results = a.probe.set_parameters("bridge_node", {"scenario.step_length": 99.0})
    assert not results[0].successful and results[0].reason
    got = a.probe.get_parameters("bridge_node", ["command_timeout", "mode", "scenario.step_length"])
    assert got == {"command_timeout": 10.0, "mode": "lockstep", "scenario.step_length": 0.1}
    # and the simulation goes on
    a.send(2, 0, sender="agent-A")
    assert a.lane(3) == 0
    assert a.proc.poll() is None
    assert a.proc.stop() == 0  # SIGINT: clean exit with the summary
    assert "bridge summary:" in a.proc.output()


def test_free_run_steps_on_its_timer_and_applies_the_latest_command(ros_graph):  # noqa: F811
    a = FakeAgent(ros_graph, mode="free_run", real_time_factor=2.0)  # a step every 0.25 s of wall time
    # nobody answers: the simulation still advances, one stamp per step
    assert a.lane(3) == 0
    stamps = sorted(ct.stamp_to_ns(m.header.stamp) for m in list(a.states))
    assert stamps[:4] == [k * STEP_NS for k in range(4)]
    a.state(4)
    a.send(4, 1)  # answered within the step period: applied at the next tick
    assert a.lane(5) == 1
    c = a.counters(at_least_steps=5)
    assert c["commands/accepted"] == 1 and c["commands/timeouts"] == 0


def test_scene_markers_are_sumos_vehicles_and_the_road_is_latched(ros_graph):  # noqa: F811
    """scene/vehicles at every step: every vehicle where libsumo (replaying the bridge's scenario and
    actions in this process) has it, with its role's colour and a stable id, DELETEs for vehicles gone at
    the next episode; scene/road reaches a subscriber that joins late (transient local)."""
    from test_scene import check_against_libsumo
    from visualization_msgs.msg import MarkerArray

    from der_ros.contract_ros import topic_qos
    from sumo_bridge.lane_change_env import LaneChangeEnv

    vehicles = ros_graph.probe.collect(ct.SCENE_VEHICLES, MarkerArray)
    # a rebuild at every reset (not the warm re-placing of the same vehicles), so that some vehicles leave
    a = FakeAgent(ros_graph, **{"scenario.max_episode_steps": 3, "scenario.ring_rebuild_every": 1})
    actions = [0, 0, 0]  # episode 0: states 0..3 (3 ends it), episode 1 starts at state 4
    for k, action in enumerate(actions):
        a.state(k)
        a.send(k, action)
    a.state(4)

    def update(k: int) -> ct.SceneUpdate:
        found = wait_for(lambda: [u for u in map(ct.parse_vehicle_markers, list(vehicles)) if u.stamp_ns == k * STEP_NS],
                         10, what=f"scene/vehicles stamped t_{k}", procs=[a.proc])  # fmt: skip
        assert len(found) == 1
        return found[0]

    env = LaneChangeEnv(ScenarioConfig.ring(max_episode_steps=3, ring_rebuild_every=1))  # the bridge's (seed 0)
    try:
        env.enable_scene()
        env.reset()
        ids = check_against_libsumo(env, update(0), need_slots=False)
        roles = set()
        for k, action in enumerate(actions, start=1):
            env.step(action)
            u = update(k)
            assert check_against_libsumo(env, u, need_slots=False) == ids  # ids stable within the episode
            assert not u.deleted
            roles |= {v.role for v in u.vehicles}
        assert {"ego", "traffic"} < roles and roles - {"ego", "traffic"}  # some neighbour slot was coloured
        before = set(env.api.vehicle.getIDList())
        env.reset()
        gone = before - set(env.api.vehicle.getIDList())
        u = update(4)
        assert gone and sorted(u.deleted) == sorted(ids[vid] for vid in gone)
        check_against_libsumo(env, u, need_slots=False)
        lanes = {lane.lane_id: lane for lane in env.lanes()}
    finally:
        env.close()

    late = a.probe.collect(ct.SCENE_ROAD, MarkerArray, qos=topic_qos(ct.SCENE_ROAD))
    road = wait_for(lambda: list(late), 10, what="the latched scene/road", procs=[a.proc])
    got = {lane.lane_id: lane for lane in ct.parse_road_markers(road[0])}
    assert set(got) == set(lanes)
    assert all(np.array_equal(got[i].points, lanes[i].points) and got[i].width == lanes[i].width for i in lanes)
    assert road[0].markers[0].header.frame_id == "map"


def test_episode_end_event_carries_the_cost_to_others(ros_graph):  # noqa: F811
    """The end event carries the env's imposed_brake and time_to_success: the same as the env gives in this
    process for the bridge's scenario (seed 0) and the same actions -- here a successful cut-in (searched
    offline: four keeps, then left) that makes the new follower brake."""
    from sumo_bridge.lane_change_env import LaneChangeEnv

    actions = [0, 0, 0, 0, 1, 0, 0, 0]
    a = FakeAgent(ros_graph, **{"scenario.max_episode_steps": len(actions), "scenario.ring_rebuild_every": 1})
    env = LaneChangeEnv(ScenarioConfig.ring(max_episode_steps=len(actions), ring_rebuild_every=1))  # the bridge's
    try:
        env.reset()
        for k, action in enumerate(actions):
            a.state(k)
            a.send(k, action)
            _obs, _r, terminated, truncated, info = env.step(action)
        assert truncated and info["event"] == "success" and info["imposed_brake"] > 0.0
    finally:
        env.close()
    ends = wait_for(lambda: [e for m in list(a.episodes) for e in ct.parse_episode_events(m) if e[1] != "start"],
                    10, what="the episode's end event", procs=[a.proc])  # fmt: skip
    _stamp, event, values = ends[0]
    assert event == "success" and values["lane_changes"] == info["lane_changes_done"] == 1
    assert values["imposed_brake"] == info["imposed_brake"]
    assert values["time_to_success"] == info["time_to_success"] == 2.5
