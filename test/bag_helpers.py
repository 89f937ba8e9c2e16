"""Helpers shared by the bag tool tests (no tests here): write bags the way the graph does.

``record_env_bag`` drives the real LaneChangeEnv and writes state / reward / command /
episode / clock messages exactly as bridge_node publishes them (der_ros.contract: reward
(naming the applied action) then state at stamp t_k = k * step, the command stamped t_k,
episode start/end events, the next episode's first state at the next stamp), returning the
ground truth the environment produced, transition by transition.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.bag.writer import BagWriter, jazzy_typestore
from der_ros.contract import applied_action_frame

TS = jazzy_typestore()
T = TS.types


def _time(ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(ns: int, frame: str = "") -> Any:
    return T["std_msgs/msg/Header"](stamp=_time(ns), frame_id=frame)


def msg_clock(ns: int) -> Any:
    return T["rosgraph_msgs/msg/Clock"](clock=_time(ns))


def msg_reward(ns: int, r: float, terminated: bool, truncated: bool, applied: int | None = None) -> Any:
    vec = T["geometry_msgs/msg/Vector3"](x=float(r), y=1.0 if terminated else 0.0, z=1.0 if truncated else 0.0)
    return T["geometry_msgs/msg/Vector3Stamped"](header=_header(ns, applied_action_frame(applied)), vector=vec)


def msg_state(ns: int, points: np.ndarray, fields: tuple[str, ...]) -> Any:
    pts = np.ascontiguousarray(points, dtype="<f8")
    pf = [T["sensor_msgs/msg/PointField"](name=n, offset=8 * i, datatype=8, count=1) for i, n in enumerate(fields)]
    step = 8 * len(fields)
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(ns, "ego"), height=1, width=pts.shape[0], fields=pf, is_bigendian=False,
        point_step=step, row_step=step * pts.shape[0], data=np.frombuffer(pts.tobytes(), dtype=np.uint8),
        is_dense=True,
    )


def msg_cmd(ns: int, action: int) -> Any:
    return T["sensor_msgs/msg/Joy"](header=_header(ns, "agent"), axes=np.zeros(0, dtype=np.float32),
                                    buttons=np.array([action], dtype=np.int32))


def msg_event(ns: int, event: str, values: dict[str, Any]) -> Any:
    kv = [T["diagnostic_msgs/msg/KeyValue"](key=k, value=repr(v) if isinstance(v, float) else str(v))
          for k, v in values.items()]
    st = T["diagnostic_msgs/msg/DiagnosticStatus"](level=1 if event == "collision" else 0, name="episode",
                                                   message=event, hardware_id="sumo_bridge", values=kv)
    return T["diagnostic_msgs/msg/DiagnosticArray"](header=_header(ns), status=[st])


def msg_metrics(ns: int, metrics: dict[str, float]) -> Any:
    kv = [T["diagnostic_msgs/msg/KeyValue"](key=k, value=repr(float(v))) for k, v in metrics.items()]
    st = T["diagnostic_msgs/msg/DiagnosticStatus"](level=0, name="agent/metrics", message="", hardware_id="", values=kv)
    return T["diagnostic_msgs/msg/DiagnosticArray"](header=_header(ns), status=[st])


GRAPH_TOPICS = (
    ("/clock", "rosgraph_msgs/msg/Clock"),
    ("/reward", "geometry_msgs/msg/Vector3Stamped"),
    ("/state", "sensor_msgs/msg/PointCloud2"),
    ("/lane_change_cmd", "sensor_msgs/msg/Joy"),
    ("/episode", "diagnostic_msgs/msg/DiagnosticArray"),
    ("/agent/metrics", "diagnostic_msgs/msg/DiagnosticArray"),
)


@dataclass
class Truth:
    """What the environment produced: transitions and per-episode statistics."""

    obs: list[np.ndarray] = field(default_factory=list)
    actions: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    next_obs: list[np.ndarray] = field(default_factory=list)
    terminated: list[bool] = field(default_factory=list)
    truncated: list[bool] = field(default_factory=list)
    episodes: list[dict[str, Any]] = field(default_factory=list)
    n_messages: int = 0


class GraphBagWriter:
    """Writes one decision step at a time in the bridge's publishing order."""

    def __init__(self, path: Path, fields: tuple[str, ...], step_ns: int = 500_000_000, **writer_kw: Any) -> None:
        self.w = BagWriter(path, **writer_kw)
        for name, typ in GRAPH_TOPICS:
            self.w.add_topic(name, typ)
        self.fields = fields
        self.step_ns = step_ns
        self.k = 0
        self.n = 0

    def _write(self, topic: str, stamp: int, sub: int, msg: Any) -> None:
        self.w.write_message(topic, stamp + sub * 1000, msg)
        self.n += 1

    def step(self, points: np.ndarray, reward: float, terminated: bool, truncated: bool,
             start_episode: int | None = None, applied: int | None = None) -> int:
        stamp = self.k * self.step_ns
        if start_episode is not None:
            self._write("/episode", stamp, 0, msg_event(stamp, "start", {"episode": start_episode, "steps": 0}))
        self._write("/clock", stamp, 1, msg_clock(stamp))
        self._write("/reward", stamp, 2, msg_reward(stamp, reward, terminated, truncated, applied))
        self._write("/state", stamp, 3, msg_state(stamp, points, self.fields))
        return stamp

    def command(self, stamp: int, action: int) -> None:
        self._write("/lane_change_cmd", stamp, 5, msg_cmd(stamp, action))

    def end_event(self, stamp: int, event: str, values: dict[str, Any]) -> None:
        self._write("/episode", stamp, 6, msg_event(stamp, event, values))

    def metrics(self, stamp: int, values: dict[str, float]) -> None:
        self._write("/agent/metrics", stamp, 7, msg_metrics(stamp, values))

    def next_stamp(self) -> None:
        self.k += 1

    def close(self) -> None:
        self.w.close()


def record_env_bag(path: Path, episodes: int = 2, seed: int = 3, max_episode_steps: int = 25,
                   policy_seed: int = 0, **writer_kw: Any) -> Truth:
    """Drive LaneChangeEnv with a random policy and record it as the graph would."""
    from sumo_bridge.lane_change_env import LaneChangeEnv
    from sumo_bridge.observation import POINT_FIELDS, field_index
    from sumo_bridge.scenario import ScenarioConfig

    env = LaneChangeEnv(ScenarioConfig(max_episode_steps=max_episode_steps, seed=seed))
    rng = np.random.default_rng(policy_seed)
    gw = GraphBagWriter(path, POINT_FIELDS, **writer_kw)
    truth = Truth()
    speed_col = field_index("speed")
    try:
        for ep in range(1, episodes + 1):
            obs, info = env.reset()
            stamp = gw.step(info["points"], 0.0, False, False, start_episode=ep)
            ret, steps, lane_changes, lane = 0.0, 0, 0, info["lane"]
            speed_sum = 0.0
            while True:
                a = int(rng.integers(3))
                gw.command(stamp, a)
                gw.next_stamp()
                nobs, r, te, tr, info = env.step(a)
                stamp = gw.step(info["points"], float(r), bool(te), bool(tr), applied=a)
                truth.obs.append(obs)
                truth.actions.append(a)
                truth.rewards.append(float(r))
                truth.next_obs.append(nobs)
                truth.terminated.append(bool(te))
                truth.truncated.append(bool(tr))
                ret += float(r)
                steps += 1
                speed_sum += float(info["points"][0, speed_col])
                if info["lane"] != lane:
                    lane_changes += 1
                lane = info["lane"]
                obs = nobs
                if te or tr:
                    event = info["event"] or ("time_limit" if tr else "collision")
                    values = {"episode": ep, "steps": steps, "return": ret, "lane_changes": lane_changes,
                              "mean_speed": float(info.get("mean_speed", speed_sum / steps))}
                    gw.end_event(stamp, event, values)
                    truth.episodes.append({"episode": ep, "outcome": event, **values})
                    gw.metrics(stamp, {"replay/h2_fraction": 0.1 * ep, "replay/h2_weight_mean": 1.0 + ep,
                                       "losses/td_loss": 0.5 / ep})
                    gw.next_stamp()
                    break
    finally:
        env.close()
    gw.close()
    truth.n_messages = gw.n
    return truth


def write_foreign_bag(path: Path, n: int = 50) -> dict[str, int]:
    """A rosbags-written bag with std_msgs/String and sensor_msgs/Imu only (no der_ros topics)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        cs = w.add_connection("/chatter", "std_msgs/msg/String", typestore=TS)
        ci = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=TS)
        for i in range(n):
            t = 1_000_000_000 + i * 50_000_000
            w.write(cs, t, TS.serialize_cdr(T["std_msgs/msg/String"](data=f"hello {i}"), "std_msgs/msg/String"))
            imu = T["sensor_msgs/msg/Imu"](
                header=_header(t, "imu"),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9), angular_velocity=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(i)),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(ci, t + 1000, TS.serialize_cdr(imu, "sensor_msgs/msg/Imu"))
    return {"/chatter": n, "/imu": n}


def write_mistyped_bag(path: Path, n: int = 5) -> None:
    """Our topic names (/state, /reward, /clock) carrying std_msgs/String: somebody else's graph."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = [w.add_connection(t, "std_msgs/msg/String", typestore=TS) for t in ("/state", "/reward", "/clock")]
        for i in range(n):
            for c in conns:
                w.write(c, 1_000_000_000 + i * 10_000_000, TS.serialize_cdr(T["std_msgs/msg/String"](data=f"m{i}"),
                                                                            "std_msgs/msg/String"))


def write_json_mcap(path: Path, n: int = 5) -> None:
    """A valid MCAP file that is no ROS bag: one JSON-encoded channel (Foxglove-style telemetry)."""
    import json

    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        schema = w.register_schema("Telemetry", "jsonschema", json.dumps({"type": "object"}).encode())
        channel = w.register_channel("/telemetry", "json", schema)
        for i in range(n):
            t = 1_000_000_000 + i * 10_000_000
            w.add_message(channel, log_time=t, publish_time=t, data=json.dumps({"i": i}).encode())
        w.finish()
