"""The scene core and its markers: every vehicle where libsumo says it is, with its role's colour and a
stable id; the road as the network's lane shapes; the marker bytes as rosbags and rclpy read them.

One libsumo simulation per process: every test closes its env before the next opens one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
import sumolib

from der_ros import contract as ct
from der_ros.bag.writer import jazzy_typestore
from der_ros.contract import road_markers_cdr, vehicle_markers_cdr
from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig
from sumo_bridge.scene import Scene

TS = jazzy_typestore()
MARKERS = "visualization_msgs/msg/MarkerArray"
CM = 0.01


@pytest.fixture
def ring() -> Iterator[LaneChangeEnv]:
    env = LaneChangeEnv(ScenarioConfig.ring(max_episode_steps=6))
    env.enable_scene()
    yield env
    env.close()


def decoded(scene: Scene, stamp: int = 0) -> ct.SceneUpdate:
    """The scene through the marker bytes and back (rosbags decoding)."""
    data = vehicle_markers_cdr(scene.vehicles, scene.removed, stamp)
    return ct.parse_vehicle_markers(TS.deserialize_cdr(data, MARKERS))


def check_against_libsumo(env: LaneChangeEnv, update: ct.SceneUpdate, need_slots: bool = True) -> dict[str, int]:
    """Every vehicle in the simulation has exactly one marker, within a centimetre of libsumo's own
    position (its front bumper = the cube's centre + half a length ahead), with libsumo's heading and
    size and the colour of its role; returns SUMO id -> marker id."""
    v = env.api.vehicle
    markers = {m.vehicle_id: m for m in update.vehicles}
    assert set(markers) == set(v.getIDList()) and len(markers) == len(update.vehicles)
    slots = {vid: slot for slot, vid in env.neighbour_ids().items() if vid is not None}
    assert slots or not need_slots, "a scene without any neighbour in a slot would not test the slot colours"
    for vid, m in markers.items():
        x, y = v.getPosition(vid)
        assert math.hypot(m.x + 0.5 * m.length * math.cos(m.yaw) - x, m.y + 0.5 * m.length * math.sin(m.yaw) - y) < CM
        assert math.isclose((90.0 - math.degrees(m.yaw)) % 360.0, v.getAngle(vid) % 360.0, abs_tol=1e-6)
        assert (m.length, m.width) == (v.getLength(vid), v.getWidth(vid))
        assert m.role == ("ego" if vid == env.ego_id else slots.get(vid, ct.TRAFFIC_ROLE))
    return {vid: m.marker_id for vid, m in markers.items()}


def test_ring_markers_are_libsumos_vehicles_with_stable_ids_and_deletes(ring: LaneChangeEnv) -> None:
    ring.reset(seed=10)
    ring.step(0)
    ids = check_against_libsumo(ring, decoded(ring.scene()))
    ring.step(1)  # a lane change: the slots change, the ids do not
    assert check_against_libsumo(ring, decoded(ring.scene())) == ids
    moved = {vid: ring.api.vehicle.getPosition(vid) for vid in ids}
    ring.reset()  # unseeded: the same vehicles re-placed (sumo_bridge.warm_state), the markers follow them
    update = decoded(ring.scene())
    assert not update.deleted and check_against_libsumo(ring, update) == ids
    assert any(math.dist(moved[vid], ring.api.vehicle.getPosition(vid)) > 1.0 for vid in ids)
    before = set(ring.api.vehicle.getIDList())
    ring.reset(seed=11)  # another placement: some ids vanish, others come
    after = set(ring.api.vehicle.getIDList())
    assert before - after, "seed 11 must drop vehicles of seed 10 for this test to check deletes"
    update = decoded(ring.scene())
    assert sorted(update.deleted) == sorted(ids[vid] for vid in before - after)
    new_ids = check_against_libsumo(ring, update)
    assert all(new_ids[vid] == ids[vid] for vid in after & before)  # same SUMO id, same marker
    assert not set(new_ids[vid] for vid in after - before) & set(ids.values())  # a new vehicle never reuses an id


def test_ring_markers_on_traci_come_from_subscriptions_and_match_the_simulation() -> None:
    """On traci (a getter is a round trip) the poses come from the per-vehicle subscriptions, on libsumo
    from getters once per decision (sumo_bridge/scene.py); both give the simulation's own poses."""
    env = LaneChangeEnv(ScenarioConfig.ring(max_episode_steps=6, backend="traci"))
    try:
        env.enable_scene()
        env.reset(seed=10)
        env.step(0)
        assert all(len(var) == 3 for var in env.api.vehicle.getAllSubscriptionResults().values())
        ids = check_against_libsumo(env, decoded(env.scene()))
        env.step(1)
        assert check_against_libsumo(env, decoded(env.scene())) == ids
    finally:
        env.close()


@pytest.mark.slow
def test_urban_markers_follow_the_new_ego_of_each_episode() -> None:
    env = LaneChangeEnv(ScenarioConfig.urban(max_episode_steps=3))
    try:
        env.enable_scene()
        env.reset(seed=5)
        first_ego = env.ego_id
        ids = check_against_libsumo(env, decoded(env.scene()))
        assert len(ids) > 100  # the bridge's traffic, not only the ego's neighbours
        for _ in range(3):
            env.step(0)
        env.reset()  # urban: the traffic runs on, a fresh ego id
        update = decoded(env.scene())
        assert env.ego_id != first_ego and ids[first_ego] in update.deleted
        check_against_libsumo(env, update)
    finally:
        env.close()


def test_scene_needs_enabling() -> None:
    env = LaneChangeEnv(ScenarioConfig.ring())
    try:
        env.reset(seed=1)
        with pytest.raises(RuntimeError, match="enable_scene"):
            env.scene()
        env.enable_scene()  # vehicles already running are subscribed now
        check_against_libsumo(env, decoded(env.scene()))
    finally:
        env.close()


@pytest.mark.parametrize("network", ["ring", "urban"])
def test_road_markers_are_the_networks_lane_shapes(network: str) -> None:
    env = LaneChangeEnv(ScenarioConfig.ring() if network == "ring" else ScenarioConfig.urban())
    try:
        data = road_markers_cdr(env.lanes(), 0, "map")
        net_file = env.network.net_file
    finally:
        env.close()
    lanes = {lane.lane_id: lane for lane in ct.parse_road_markers(TS.deserialize_cdr(data, MARKERS))}
    # sumolib reads the .net.xml itself: an independent source of the shapes
    net = sumolib.net.readNet(str(net_file), withInternal=True)
    expected = {lane.getID(): lane for edge in net.getEdges(withInternal=True) for lane in edge.getLanes()}
    assert set(lanes) == set(expected) and len(lanes) > 10
    for lane_id, lane in lanes.items():
        want = np.asarray(expected[lane_id].getShape(), dtype=np.float64)
        assert lane.points.shape == want.shape and np.abs(lane.points - want).max() < CM, lane_id
        assert lane.width == pytest.approx(expected[lane_id].getWidth())


def _markers(n: int) -> list[ct.VehicleMarker]:
    roles = ct.SCENE_ROLES
    return [ct.VehicleMarker(i * 3, f"veh.{'x' * (i % 5)}{i}", roles[i % len(roles)], 1.5 * i - 7.0, 0.25 * i,
                             0.37 * i - 2.0, 4.0 + 0.1 * i, 1.6 + 0.05 * i) for i in range(n)]  # fmt: skip


def test_marker_bytes_are_what_rosbags_writes_and_rclpy_reads() -> None:
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray

    markers = _markers(11)  # ids of every length: the alignment of the fields after them moves
    data = vehicle_markers_cdr(markers, [5, 40], 3_500_000_001, "map")
    msg = TS.deserialize_cdr(data, MARKERS)
    assert bytes(TS.serialize_cdr(msg, MARKERS)) == data
    live = deserialize_message(data, MarkerArray)
    for update in (ct.parse_vehicle_markers(msg), ct.parse_vehicle_markers(live)):
        assert update.stamp_ns == 3_500_000_001 and update.deleted == [5, 40] and not update.delete_all
        for got, want in zip(update.vehicles, markers, strict=True):
            assert got._replace(yaw=0.0) == want._replace(yaw=0.0)
            assert math.isclose(math.remainder(got.yaw - want.yaw, math.tau), 0.0, abs_tol=1e-12)
    m = live.markers[0]
    assert (m.header.frame_id, m.ns, m.type, m.action) == ("map", ct.VEHICLE_NS, m.CUBE, m.ADD)
    assert m.pose.position.z == pytest.approx(0.5 * ct.VEHICLE_HEIGHT) and m.scale.z == ct.VEHICLE_HEIGHT
    assert (m.color.r, m.color.g, m.color.b) == pytest.approx(ct.ROLE_COLOURS[markers[0].role][:3], abs=1e-6)
    assert live.markers[-1].action == m.DELETE and live.markers[-1].id == 40

    lane = ct.LaneLine(":j_0_0", np.array([[0.0, 1.0], [2.5, 3.0], [4.0, -1.0]]), 3.2)
    road = deserialize_message(road_markers_cdr([lane], 0, "map"), MarkerArray)
    assert (road.markers[0].type, road.markers[0].text, road.markers[0].scale.x) == (road.markers[0].LINE_STRIP,
                                                                                      ":j_0_0", 3.2)  # fmt: skip
    (back,) = ct.parse_road_markers(road)
    assert np.array_equal(back.points, lane.points)


def test_malformed_markers_are_named() -> None:
    bad_role = _markers(1)[0]._replace(role="bus")
    with pytest.raises(ValueError, match="role = 'bus'"):
        vehicle_markers_cdr([bad_role], [], 0)
    msg = TS.deserialize_cdr(vehicle_markers_cdr(_markers(2), [], 0), MARKERS)
    msg.markers[1].color.g = 0.123
    with pytest.raises(ValueError, match=r"colour = \(.*0\.123"):
        ct.parse_vehicle_markers(msg)
    msg.markers[1].type = ct.MARKER_LINE_STRIP
    with pytest.raises(ValueError, match="marker 1 .*type = 4, expected CUBE"):
        ct.parse_vehicle_markers(msg)
    with pytest.raises(ValueError, match="stamp = -1"):
        vehicle_markers_cdr([], [], -1)
