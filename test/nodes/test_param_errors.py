"""A bad node parameter is one line ``origin/node/name = value: reason`` -- from ``der graph`` before any
process starts, and from the node itself (real node processes) -- never an rclpy traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from ros_harness import ros_domain, ros_graph  # noqa: F401 - fixtures

from der_ros.configuration import ConfigError
from der_ros.nodes.params import build_graph_params, load_params_file

REPO = Path(__file__).resolve().parents[2]
PARAMS = REPO / "config" / "graph.params.yaml"


def der_graph(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "der_ros.cli", "graph", "--steps", "20", "--eval-interval", "0",
                           "--final-eval-episodes", "0", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=120)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("agent_node:replay.lam=7", "-p/agent_node/replay.lam = 7: expected >= 0.0 and <= 1.0"),
        ("agent_node:agent.lr=abc", "-p/agent_node/agent.lr = 'abc': expected a number"),
        ("agent_node:agent.batch_size=0", "-p/agent_node/agent.batch_size = 0: expected >= 1"),
        ("bridge_node:command_timeout=-1", "-p/bridge_node/command_timeout = -1: expected > 0.0"),
        ("agent_node:agent.lr=.inf", "-p/agent_node/agent.lr = inf: expected a finite number"),
        ("agent_node:agent.epsilon_end=0.9", "-p/agent_node/agent.epsilon_end = 0.9: expected <= epsilon_start (0.5)"),
        ("recorder_node:compression=bz2", "-p/recorder_node/compression = 'bz2': expected one of 'none', 'zstd', 'lz4'"),
        ("agent_node:agent.bogus=1", "-p/agent_node/agent.bogus = 1: agent_node has no parameter 'agent.bogus'"),
        ("agent_node:replay.capacity=100", "-p/agent_node/agent.batch_size = 128: expected <= replay.capacity (100)"),
        ("agent_node:replay.capacity=1000000000000",
         "-p/agent_node/replay.capacity = 1000000000000: replay buffer H1 (capacity=1000000000000, obs_shape=(29,)"),
    ],
)
def test_der_graph_rejects_a_bad_parameter_before_any_process_starts(tmp_path: Path, override: str, line: str) -> None:
    run_dir = tmp_path / "run"
    extra = ["-p", "agent_node:agent.epsilon_start=0.5"] if "epsilon_end" in override else []
    res = der_graph("--run-dir", str(run_dir), *extra, "-p", override)
    assert res.returncode == 2, res.stderr
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"der graph: configuration error: {line}"), res.stderr
    assert not run_dir.exists()  # nothing started, nothing written


@pytest.mark.slow
def test_der_graph_names_the_params_file_of_a_bad_value_and_rejects_binary_garbage(tmp_path: Path) -> None:
    doc = yaml.safe_load(PARAMS.read_text())
    doc["agent_node"]["ros__parameters"]["replay.capacity"] = -5
    bad = tmp_path / "bad.params.yaml"
    bad.write_text(yaml.safe_dump(doc))
    res = der_graph("--run-dir", str(tmp_path / "run"), "--params", str(bad))
    assert res.returncode == 2
    assert res.stderr.strip() == f"der graph: configuration error: {bad}/agent_node/replay.capacity = -5: expected >= 1"
    garbage = tmp_path / "garbage.yaml"
    garbage.write_bytes(bytes(range(120, 256)) * 3)
    res = der_graph("--run-dir", str(tmp_path / "run"), "--params", str(garbage))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert f"{garbage}: not a text file: byte 0x80 at offset 8 is not UTF-8" in res.stderr
    assert not (tmp_path / "run").exists()


def test_graph_params_are_typed_for_ros_and_flags_are_named(tmp_path: Path) -> None:
    """rclpy refuses an integer for a double parameter: the run's params file carries floats."""
    doc = load_params_file(PARAMS)
    doc["agent_node"]["ros__parameters"]["agent.lr"] = 1
    doc["bridge_node"]["ros__parameters"]["scenario.urban_depart_pos"] = [40, 400]
    params = build_graph_params(doc, steps=5, scenario="ring", run_dir=tmp_path, lam=1, base_name="f.yaml")
    agent = params["agent_node"]["ros__parameters"]
    assert isinstance(agent["agent.lr"], float) and isinstance(agent["replay.lam"], float)
    assert params["bridge_node"]["ros__parameters"]["scenario.urban_depart_pos"] == [40.0, 400.0]
    assert all(isinstance(x, float) for x in params["bridge_node"]["ros__parameters"]["scenario.urban_depart_pos"])
    with pytest.raises(ConfigError, match=r"^--lam/agent_node/replay.lam = 7: expected >= 0.0 and <= 1.0$"):
        build_graph_params(doc, steps=5, scenario="ring", run_dir=tmp_path, lam=7, base_name="f.yaml")
    doc["agent_node"]["ros__parameters"]["agent.typo"] = 3
    with pytest.raises(ConfigError, match=r"^f.yaml/agent_node/agent.typo = 3: agent_node has no parameter"):
        build_graph_params(doc, steps=5, scenario="ring", run_dir=tmp_path, base_name="f.yaml")


@pytest.mark.ros
@pytest.mark.parametrize(
    ("module", "params", "line"),
    [
        ("der_ros.nodes.agent_node", {"replay.lam": 7.0}, "-p/agent_node/replay.lam = 7.0: expected >= 0.0 and <= 1.0"),
        ("der_ros.nodes.agent_node", {"agent.lr": 1},
         "-p/agent_node/agent.lr = 1: expected a floating-point number (a ROS double parameter: write 1.0)"),
        ("der_ros.nodes.agent_node", {"agent.epsilon_start": 0.1, "agent.epsilon_end": 0.5},
         "-p/agent_node/agent.epsilon_end = 0.5: expected <= epsilon_start (0.1)"),
        ("der_ros.nodes.bridge_node", {"command_timeout": -1.0}, "-p/bridge_node/command_timeout = -1.0: expected > 0.0"),
        ("der_ros.nodes.bridge_node", {"scenario.observation.speed_scale": 0.0},
         "-p/bridge_node/scenario.observation.speed_scale = 0.0: expected >= 0.1"),
    ],
    ids=["range", "type", "cross-field", "bridge", "nested"],
)
def test_a_node_turns_a_rejected_parameter_into_one_line(ros_graph, module: str, params: dict, line: str) -> None:  # noqa: F811
    proc = ros_graph.start_node(module, params=params)
    assert proc.wait(timeout=60) == 1
    out = proc.output()
    assert "Traceback" not in out and "Exception" not in out
    errors = [x for x in out.splitlines() if "ERROR" in x]
    assert len(errors) == 1 and errors[0].endswith(f"could not start: {line}"), out


@pytest.mark.ros
def test_a_node_names_its_params_file(ros_graph, tmp_path: Path) -> None:  # noqa: F811
    params_file = tmp_path / "p.yaml"
    params_file.write_text(yaml.safe_dump({"agent_node": {"ros__parameters": {"agent.batch_size": 0}}}))
    proc = ros_graph.start_node("der_ros.nodes.agent_node", params_file=params_file)
    assert proc.wait(timeout=60) == 1
    assert f"could not start: {params_file}/agent_node/agent.batch_size = 0: expected >= 1" in proc.output()
    assert "Traceback" not in proc.output()


# -- issue 45, finding 3: files, paths and flags are checked before any process starts --------------------
def _refused(tmp_path: Path, *args: str) -> str:
    run_dir = tmp_path / "run"
    res = der_graph("--run-dir", str(run_dir), *args)
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert res.returncode == 2, res.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("der graph: configuration error: "), res.stderr[-2000:]
    assert not run_dir.exists()  # nothing started, nothing written
    return lines[0].removeprefix("der graph: configuration error: ")


def test_der_graph_refuses_a_missing_or_foreign_checkpoint_in(tmp_path: Path) -> None:
    missing = tmp_path / "nope.pt"
    assert _refused(tmp_path, "-p", f"agent_node:checkpoint_in={missing}") == (
        f"-p/agent_node/checkpoint_in = '{missing}': no such file")
    foreign = tmp_path / "notes.pt"
    foreign.write_text("not a checkpoint\n")
    line = _refused(tmp_path, "-p", f"agent_node:checkpoint_in={foreign}")
    assert line.startswith(f"-p/agent_node/checkpoint_in = '{foreign}': not a der_ros checkpoint (UnpicklingError")


def test_der_graph_refuses_a_checkpoint_of_another_shape(tmp_path: Path) -> None:
    from der_ros.agent.config import DQNConfig
    from der_ros.agent.dqn import DQNAgent
    from der_ros.replay.config import ReplayConfig

    ckpt = tmp_path / "cartpole.pt"
    DQNAgent((4,), __import__("numpy").float32, 2, DQNConfig(), ReplayConfig(capacity=256, kind="uniform")).save(ckpt)
    line = _refused(tmp_path, "-p", f"agent_node:checkpoint_in={ckpt}")
    assert line.startswith(f"-p/agent_node/checkpoint_in = '{ckpt}': a checkpoint for observations (4,) and 2 actions")


def test_der_graph_refuses_an_output_it_cannot_write(tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert _refused(tmp_path, "-p", f"recorder_node:output={blocker}/bag") == (
        f"-p/recorder_node/output = '{blocker}/bag': cannot be created: {blocker} is not a directory")
    full = tmp_path / "full_bag"
    (full / "old").mkdir(parents=True)
    assert _refused(tmp_path, "-p", f"recorder_node:output={full}") == (
        f"-p/recorder_node/output = '{full}': exists and is not empty (not overwriting)")
    assert _refused(tmp_path, "-p", f"agent_node:checkpoint_out={tmp_path}") == (
        f"-p/agent_node/checkpoint_out = '{tmp_path}': is a directory, expected a file path")


def test_der_graph_refuses_a_params_file_that_is_not_a_ros_params_file(tmp_path: Path) -> None:
    train_cfg = REPO / "config" / "ring.yaml"  # a training config, not a ROS params file
    line = _refused(tmp_path, "--params", str(train_cfg))
    assert line.startswith(f"{train_cfg}: top-level key ") and "is not a node of the graph" in line
    flat = tmp_path / "flat.params.yaml"
    flat.write_text("agent_node:\n  agent.lr: 0.001\n")  # the values without ros__parameters
    assert _refused(tmp_path, "--params", str(flat)) == (
        f"{flat}: section 'agent_node' is not a ROS params section: expected exactly the key ros__parameters, "
        "found 'agent.lr'")


@pytest.mark.parametrize("steps", ["0", "-3"])
def test_der_graph_refuses_a_number_of_steps_below_one_with_exit_2(tmp_path: Path, steps: str) -> None:
    res = subprocess.run([sys.executable, "-m", "der_ros.cli", "graph", "--run-dir", str(tmp_path / "run"),
                          "--steps", steps], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and res.stderr.strip() == f"der graph: configuration error: --steps = {steps}, expected >= 1"
    assert not (tmp_path / "run").exists()


def test_der_graph_refuses_an_agent_step_that_is_not_the_bridges(tmp_path: Path) -> None:
    assert _refused(tmp_path, "-p", "agent_node:step_seconds=0") == (
        "-p/agent_node/step_seconds = 0.0: expected the bridge's step, 0.5 s (scenario.step_length x "
        "scenario.decision_interval)")
    line = _refused(tmp_path, "-p", "bridge_node:scenario.decision_interval=2")
    assert line.startswith(f"{PARAMS}/agent_node/step_seconds = 0.5: expected the bridge's step, 0.2 s")


def test_der_graph_refuses_a_lying_params_file(tmp_path: Path) -> None:
    """Issue 45, finding 2 through der graph: a repeated section, deep nesting, a huge value -- one line each."""
    text = PARAMS.read_text()
    dup = tmp_path / "dup.params.yaml"
    dup.write_text(text + "\nagent_node:\n  ros__parameters:\n    agent.lr: 100\n")
    first = next(i for i, x in enumerate(text.splitlines(), 1) if x.startswith("agent_node:"))
    line = len(text.splitlines()) + 2
    assert _refused(tmp_path, "--params", str(dup)) == (
        f"{dup}: line {line}: key 'agent_node': duplicate key (first at line {first})")
    deep = tmp_path / "deep.params.yaml"
    deep.write_text("agent_node: " + "[" * 3000 + "]" * 3000 + "\n")
    assert _refused(tmp_path, "--params", str(deep)).endswith("nested deeper than 64 levels")
    huge = tmp_path / "huge.params.yaml"
    huge.write_text("agent_node:\n  ros__parameters:\n    device: " + "x" * 3_000_000 + "\n")
    assert len(_refused(tmp_path, "--params", str(huge))) < 200
