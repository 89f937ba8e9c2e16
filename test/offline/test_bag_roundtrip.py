"""Round trips: environment -> bag (as the graph records it) -> info / export / plot, and the CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from bag_helpers import GraphBagWriter, record_env_bag, write_foreign_bag

from der_ros.bag.reader import BagError, BagReader
from der_ros.cli import main as der_main
from der_ros.offline.bag_cli import INFO_SCHEMA_VERSION, bag_info
from der_ros.offline.bag_plots import plot_bags
from der_ros.offline.episodes import iter_steps, resolve_topics, scan_bag
from der_ros.offline.export import build_transitions, load_transitions, save_transitions


@pytest.fixture(scope="module")
def env_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    path = tmp_path_factory.mktemp("env") / "bag"
    truth = record_env_bag(path, episodes=4, seed=3, max_episode_steps=25)
    return path, truth


def test_export_matches_the_environment_bit_for_bit(env_bag: tuple[Path, object], tmp_path: Path) -> None:
    path, truth = env_bag
    tr = build_transitions(BagReader(path))
    assert len(tr) == len(truth.actions) > 5
    assert tr.skipped == {}
    assert tr.obs.dtype == np.float32 and tr.next_obs.dtype == np.float32
    # bit-identical observations (compare the bytes, not approximately)
    assert tr.obs.tobytes() == np.asarray(truth.obs, dtype=np.float32).tobytes()
    assert tr.next_obs.tobytes() == np.asarray(truth.next_obs, dtype=np.float32).tobytes()
    assert tr.actions.tolist() == truth.actions
    assert tr.rewards.tolist() == truth.rewards  # float64, exact
    assert tr.terminated.tolist() == truth.terminated
    assert tr.truncated.tolist() == truth.truncated
    # episodes are numbered in bag order; the last transition of each is terminal or truncated
    ends = np.flatnonzero(np.diff(tr.episode))
    assert np.all(tr.terminated[ends] | tr.truncated[ends])
    assert int(tr.episode.max()) + 1 == len(truth.episodes)
    # file round trips
    for suffix in (".npz", ".parquet"):
        out = save_transitions(tr, tmp_path / f"t{suffix}")
        back = load_transitions(out)
        for k, v in tr.arrays().items():
            got = getattr(back, k)
            assert got.dtype == v.dtype and np.array_equal(got, v), (suffix, k)


def test_info_reproduces_the_episodes(env_bag: tuple[Path, object]) -> None:
    path, truth = env_bag
    info = bag_info(path)
    assert info["schema_version"] == INFO_SCHEMA_VERSION
    assert not info["truncated"] and not info["metadata_stale"]
    assert info["message_count"] == truth.n_messages
    counts = {t["name"]: t["count"] for t in info["topics"]}
    n_steps = len(truth.actions) + len(truth.episodes)
    assert counts["/state"] == counts["/reward"] == counts["/clock"] == n_steps
    assert counts["/lane_change_cmd"] == len(truth.actions)
    assert counts["/episode"] == 2 * len(truth.episodes)
    qos = {t["name"]: t["qos_text"] for t in info["topics"]}
    assert qos["/state"] == "RELIABLE, KEEP_LAST 50" and qos["/clock"] == "BEST_EFFORT, KEEP_LAST 1"
    got = [(e["episode"], e["steps"], e["return"], e["lane_changes"], e["outcome"], e["mean_speed"])
           for e in info["episodes"]]
    want = [(e["episode"], e["steps"], e["return"], e["lane_changes"], e["outcome"], e["mean_speed"])
            for e in truth.episodes]
    assert got == want
    assert info["summary"]["outcomes"]["success"] == sum(e["outcome"] == "success" for e in truth.episodes)


def test_episode_statistics_without_episode_events(env_bag: tuple[Path, object], tmp_path: Path) -> None:
    """Without the bridge's events, steps / return / lane changes are computed from the steps."""
    path, truth = env_bag
    # re-record the same bag minus the episode topic: copy through the reader
    from der_ros.bag.writer import BagWriter

    dst = tmp_path / "noevents"
    w = BagWriter(dst)
    r = BagReader(path)
    for t, c in r.topics().items():
        if t != "/episode":
            w.add_topic(t, c.msgtype)
    for m in r.messages():
        if m.topic != "/episode":
            w.write(m.topic, m.log_time, bytes(m.data))
    w.close()
    scan = scan_bag(BagReader(dst))
    assert [e.source for e in scan.episodes] == ["steps"] * len(truth.episodes)
    assert [e.steps for e in scan.episodes] == [e["steps"] for e in truth.episodes]
    assert [e.ret for e in scan.episodes] == pytest.approx([e["return"] for e in truth.episodes], abs=1e-9)
    assert [e.lane_changes for e in scan.episodes] == [e["lane_changes"] for e in truth.episodes]
    # from the flags alone: a collision is 'terminated'; the horizon (a success there included) 'time_limit'
    outcome = {"success": "time_limit", "collision": "terminated", "time_limit": "time_limit"}
    assert [e.outcome for e in scan.episodes] == [outcome[e["outcome"]] for e in truth.episodes]


def test_synthetic_sequence_with_reordered_topics_and_missing_command(tmp_path: Path) -> None:
    """A bag whose rewards do not name the applied action (older bridges): the commands give the
    actions; recorded late (after the next state) they still align by stamp; a missing one is skipped."""
    fields = ("x", "y", "z", "speed", "rel_speed", "gap", "lane", "target_lane", "present", "slot", "lane_count", "length")
    from sumo_bridge.observation import ObservationConfig, empty_points, encode_observation

    gw = GraphBagWriter(tmp_path / "b", fields)
    pts = []
    for k in range(6):
        p = empty_points()
        p[0, 3] = 5.0 + k  # speed
        p[0, 6] = 0.0 if k < 3 else 1.0  # lane change at k = 3
        p[0, 10] = 2.0
        pts.append(p)
    stamps = []
    for k in range(6):
        stamps.append(gw.step(pts[k], 0.0 if k == 0 else float(k), False, k == 5, start_episode=1 if k == 0 else None))
        if k >= 1 and k != 3:  # command for step k-1 arrives after state k; the one for step 2 is lost
            gw.command(stamps[k - 1], k % 3)
        gw.next_stamp()
    gw.close()
    tr = build_transitions(BagReader(tmp_path / "b"))
    assert tr.skipped == {"no_command": 1}  # step 2; step 5 is the last (truncated) state
    assert tr.stamps_ns.tolist() == [stamps[0], stamps[1], stamps[3], stamps[4]]
    assert tr.actions.tolist() == [1, 2, 1, 2]
    assert tr.rewards.tolist() == [1.0, 2.0, 4.0, 5.0]
    assert tr.truncated.tolist() == [False, False, False, True]
    cfg = ObservationConfig()
    assert np.array_equal(tr.obs[2], encode_observation(pts[3], cfg))
    assert np.array_equal(tr.next_obs[2], encode_observation(pts[4], cfg))
    scan = scan_bag(BagReader(tmp_path / "b"))
    (ep,) = scan.episodes
    assert (ep.steps, ep.ret, ep.lane_changes, ep.outcome) == (5, 15.0, 1, "time_limit")
    assert ep.mean_speed == pytest.approx(np.mean([6, 7, 8, 9, 10]))


def test_export_stores_the_applied_action_not_the_command(tmp_path: Path) -> None:
    """After a timeout the bridge applies its default (0), names it in the next reward, and the
    export stores that -- as the online learner does -- not the late command."""
    from sumo_bridge.observation import POINT_FIELDS, empty_points

    gw = GraphBagWriter(tmp_path / "b", POINT_FIELDS)
    commanded = [2, 1, 2, 1]
    applied = [2, 0, 0, 1]  # steps 1 and 2 timed out: the bridge kept the lane
    stamps = [gw.step(empty_points(), 0.0, False, False, start_episode=1)]
    for k, (cmd, app) in enumerate(zip(commanded, applied)):
        gw.command(stamps[k], cmd)
        gw.next_stamp()
        stamps.append(gw.step(empty_points(), float(k), False, k == 3, applied=app))
    gw.close()
    tr = build_transitions(BagReader(tmp_path / "b"))
    assert tr.actions.tolist() == applied
    assert tr.overridden == 2 and tr.skipped == {}
    # a timed-out step whose command was never recorded is still a transition: the reward names the action
    gw = GraphBagWriter(tmp_path / "c", POINT_FIELDS)
    s0 = gw.step(empty_points(), 0.0, False, False, start_episode=1)
    gw.next_stamp()
    gw.step(empty_points(), 1.0, False, True, applied=0)
    gw.close()
    tr = build_transitions(BagReader(tmp_path / "c"))
    assert tr.actions.tolist() == [0] and tr.stamps_ns.tolist() == [s0] and tr.overridden == 0


def test_cli_info_json_schema_and_text(env_bag: tuple[Path, object], capsys: pytest.CaptureFixture[str]) -> None:
    path, truth = env_bag
    assert der_main(["bag", "info", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    schema = {
        "schema_version": int, "bag": str, "name": str, "files": list, "truncated": bool, "metadata_yaml": bool,
        "metadata_stale": bool, "message_count": int, "start_ns": int, "end_ns": int, "duration_s": float,
        "topics": list, "roles": dict, "steps": int, "episodes": list, "summary": dict, "metrics": list,
        "skipped": dict,
    }
    assert set(doc) == set(schema)
    for k, typ in schema.items():
        assert isinstance(doc[k], typ), k
    for t in doc["topics"]:
        assert set(t) == {"name", "type", "count", "qos", "qos_text", "role"}
    for e in doc["episodes"]:
        assert set(e) == {"index", "episode", "start_s", "end_s", "steps", "return", "lane_changes", "outcome",
                          "mean_speed", "source"}
        assert e["outcome"] in ("success", "collision", "time_limit")
    assert set(doc["summary"]) == {"episodes", "finished_episodes", "outcomes", "success_rate", "collision_rate",
                                   "mean_return"}
    assert doc["metrics"] == ["losses/td_loss", "replay/h2_fraction", "replay/h2_weight_mean"]
    assert doc["roles"]["state"] == "/state"
    assert der_main(["bag", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "/state" in text and "sensor_msgs/msg/PointCloud2" in text and "RELIABLE, KEEP_LAST 50" in text
    assert f"{len(truth.episodes)} finished episodes" in text


def test_der_replay_is_the_old_spelling_of_der_bag(env_bag: tuple[Path, object],
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """``der bag`` was ``der replay`` before issue 42; scripts that spell it the old way still work."""
    path, _truth = env_bag
    assert der_main(["bag", "info", str(path), "--json"]) == 0
    new = json.loads(capsys.readouterr().out)
    assert der_main(["replay", "info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == new
    assert der_main(["replay", "export", str(path), "--to", "t.csv"]) == 2
    assert "der bag export: --to t.csv" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_export_and_plot(env_bag: tuple[Path, object], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, truth = env_bag
    out = tmp_path / "t.npz"
    assert der_main(["bag", "export", str(path), "--to", str(out)]) == 0
    assert np.array_equal(np.load(out)["actions"], truth.actions)
    assert der_main(["bag", "export", str(path), "--to", str(tmp_path / "t.csv")]) == 2
    plots = tmp_path / "plots"
    assert der_main(["bag", "plot", str(path), str(path), "--label", "a", "--label", "b", "--out", str(plots)]) == 0
    names = {p.name for p in plots.iterdir()}
    assert {"returns.png", "outcomes.png", "speed.png", "der_replay.png", "metrics.png", "topic_rates.png"} <= names
    for p in plots.iterdir():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000


@pytest.mark.slow
def test_foreign_bag_info_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    counts = write_foreign_bag(tmp_path / "foreign", n=60)
    info = bag_info(tmp_path / "foreign")
    assert {t["name"]: t["count"] for t in info["topics"]} == counts
    assert {t["name"]: t["type"] for t in info["topics"]} == {"/chatter": "std_msgs/msg/String", "/imu": "sensor_msgs/msg/Imu"}
    assert info["episodes"] == [] and info["roles"] == {} and info["steps"] == 0
    assert info["duration_s"] == pytest.approx((59 * 50_000_000 + 1000) / 1e9)
    files = plot_bags([tmp_path / "foreign"], tmp_path / "plots")
    assert [f.name for f in files] == ["topic_rates.png"]
    assert der_main(["bag", "info", str(tmp_path / "foreign")]) == 0
    assert "no episodes" in capsys.readouterr().out
    with pytest.raises(BagError, match="no state, reward topic"):
        build_transitions(BagReader(tmp_path / "foreign"))


def test_cli_cut_and_corrupted_bags(env_bag: tuple[Path, object], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    path, truth = env_bag
    src = next(path.glob("*.mcap"))
    raw = src.read_bytes()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / src.name).write_bytes(raw[: len(raw) * 2 // 3])
    shutil.copy(path / "metadata.yaml", cut / "metadata.yaml")
    assert der_main(["bag", "info", str(cut), "--json"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert doc["truncated"] and doc["metadata_stale"]
    assert "truncated" in captured.err and str(cut / src.name) in captured.err
    assert 0 < doc["message_count"] < truth.n_messages
    # a flipped byte in an (uncompressed) chunk: the record holding it is dropped, with one warning, and
    # info reports it; the chunk's other records are read
    bad = tmp_path / "bad"
    bad.mkdir()
    flipped = bytearray(raw)
    flipped[len(raw) // 3] ^= 0x5A
    (bad / src.name).write_bytes(bytes(flipped))
    assert der_main(["bag", "info", str(bad), "--json"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    (chunk,) = doc["skipped"]["ranges"]
    assert doc["skipped"]["chunks"] == 1 and doc["skipped"]["messages_lost"] == chunk["messages_lost"] == 1
    assert chunk["start"] < len(raw) // 3 < chunk["end"] and chunk["damaged_at"] == len(raw) // 3
    assert chunk["dropped"][0] <= len(raw) // 3 < chunk["dropped"][1]
    assert doc["skipped"]["bytes"] == chunk["dropped"][1] - chunk["dropped"][0]
    assert doc["message_count"] == truth.n_messages - 1
    assert captured.err.count(f"damaged byte at {len(raw) // 3}") == 1 and f"bytes {chunk['start']}-{chunk['end']}" in captured.err
    assert der_main(["bag", "info", str(bad)]) == 0
    assert f"DAMAGED:   1 chunk(s) damaged (one byte at {len(raw) // 3}, 1 record dropped)" in capsys.readouterr().out
    # damage the framing of a bag without chunk index (a killed recorder's): a clean one-line error
    worse = tmp_path / "worse"
    worse.mkdir()
    cut_raw = bytearray(raw[: len(raw) * 2 // 3])
    cut_raw[8] ^= 0xFF  # the header record's opcode
    (worse / src.name).write_bytes(bytes(cut_raw))
    assert der_main(["bag", "info", str(worse)]) == 1
    err = capsys.readouterr().err
    assert "error:" in err and str(worse / src.name) in err and "byte offset" in err
    assert "Traceback" not in err


def test_namespaced_topics_resolve(tmp_path: Path) -> None:
    from der_ros.bag.writer import BagWriter

    w = BagWriter(tmp_path / "ns")
    w.add_topic("/run1/state", "sensor_msgs/msg/PointCloud2")
    w.add_topic("/run2/state", "sensor_msgs/msg/PointCloud2")
    w.add_topic("/run2/reward", "geometry_msgs/msg/Vector3Stamped")
    w.add_topic("/run2/episode", "std_msgs/msg/String")  # wrong type: not the episode topic
    w.close()
    r = BagReader(tmp_path / "ns")
    assert resolve_topics(r, "/run2") == {"state": "/run2/state", "reward": "/run2/reward"}
    assert resolve_topics(r, "run1") == {"state": "/run1/state"}


def test_observation_config_from_the_bag_or_the_run(tmp_path: Path) -> None:
    """export uses the agent's observation scales: bag custom_data, else der graph's params.yaml."""
    from der_ros.offline.export import OBS_CONFIG_KEY, observation_config_of
    from sumo_bridge.observation import ObservationConfig, encode_observation

    truth_default = record_env_bag(tmp_path / "run" / "bag", episodes=1, max_episode_steps=5)
    tr_default = build_transitions(BagReader(tmp_path / "run" / "bag"))
    assert np.array_equal(tr_default.obs, np.asarray(truth_default.obs))
    (tmp_path / "run" / "params.yaml").write_text(
        "bridge_node:\n  ros__parameters:\n    scenario.observation.speed_scale: 40.0\n"
        "agent_node:\n  ros__parameters:\n    observation.speed_scale: 10.0\n    observation.neighbour_range: 15.0\n")
    cfg = observation_config_of(BagReader(tmp_path / "run" / "bag"))
    assert (cfg.speed_scale, cfg.neighbour_range, cfg.max_lanes) == (10.0, 15.0, 3)
    tr = build_transitions(BagReader(tmp_path / "run" / "bag"))
    pts0 = next(s.points for s in iter_steps(BagReader(tmp_path / "run" / "bag"), {"state": "/state"}))
    assert np.array_equal(tr.obs[0], encode_observation(pts0, cfg))
    assert not np.array_equal(tr.obs[0], tr_default.obs[0])  # speed feature scaled differently
    # custom_data in the bag wins over params.yaml
    from der_ros.bag.writer import BagWriter

    w = BagWriter(tmp_path / "run2" / "bag", custom_data={OBS_CONFIG_KEY: '{"speed_scale": 5.0}'})
    w.close()
    assert observation_config_of(BagReader(tmp_path / "run2" / "bag")) == ObservationConfig(speed_scale=5.0)


def test_long_bag_with_late_commands_beyond_several_steps(tmp_path: Path) -> None:
    """More steps than the reorder window, commands logged 3 steps late: every transition aligns."""
    from sumo_bridge.observation import POINT_FIELDS, empty_points

    gw = GraphBagWriter(tmp_path / "long", POINT_FIELDS, flush_every_messages=5000)
    n = 700
    stamps: list[int] = []
    for k in range(n):
        p = empty_points()
        p[0, 3] = float(k % 17)
        stamps.append(gw.step(p, float(k), False, k == n - 1, start_episode=0 if k == 0 else None))
        if k >= 3:
            gw.command(stamps[k - 3], (k - 3) % 3)
        gw.next_stamp()
    for j in range(n - 3, n - 1):  # the remaining commands (none for the final, truncated state)
        gw.command(stamps[j], j % 3)
    gw.close()
    tr = build_transitions(BagReader(tmp_path / "long"))
    assert len(tr) == n - 1 and tr.skipped == {}
    assert tr.actions.tolist() == [k % 3 for k in range(n - 1)]
    assert tr.rewards.tolist() == [float(k) for k in range(1, n)]
    assert tr.stamps_ns.tolist() == stamps[:-1]
    assert tr.truncated.tolist() == [False] * (n - 2) + [True]


def test_bare_mcap_from_mcap_ros2_support_works_with_info_and_plot(tmp_path: Path) -> None:
    """An .mcap written by mcap-ros2-support (no metadata.yaml, no QoS) with two graph topics."""
    from mcap_ros2.writer import Writer

    f = tmp_path / "bare.mcap"
    reward_def = ("std_msgs/Header header\ngeometry_msgs/Vector3 vector\n" + "=" * 80 + "\nMSG: std_msgs/Header\n"
                  "builtin_interfaces/Time stamp\nstring frame_id\n" + "=" * 80 + "\nMSG: builtin_interfaces/Time\n"
                  "int32 sec\nuint32 nanosec\n" + "=" * 80 + "\nMSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n")
    with open(f, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef("geometry_msgs/msg/Vector3Stamped", reward_def)
        for k in range(8):  # two episodes of 4 states, the 4th truncated
            msg = {"header": {"stamp": {"sec": k, "nanosec": 0}, "frame_id": ""},
                   "vector": {"x": float(k % 4), "y": 0.0, "z": 1.0 if k % 4 == 3 else 0.0}}
            w.write_message("/reward", schema, msg, log_time=k * 1_000_000_000, publish_time=k)
        w.finish()
    info = bag_info(f)
    assert not info["metadata_yaml"] and info["roles"] == {"reward": "/reward"}
    assert info["topics"][0]["count"] == 8 and info["topics"][0]["qos_text"] == "-"
    assert [(e["steps"], e["return"], e["outcome"]) for e in info["episodes"]] == [(3, 6.0, "time_limit")] * 2
    assert info["duration_s"] == 7.0
    assert [p.name for p in plot_bags([f], tmp_path / "plots")] == ["returns.png", "outcomes.png", "topic_rates.png"]
