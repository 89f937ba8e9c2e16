"""`der train` on bad inputs: every config problem is one error before anything is written, every float
field is finite, and --resume takes a checkpoint of der graph's agent node (or refuses it in one sentence)."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_harness import ros_domain, ros_graph  # noqa: F401 - fixtures

import der_ros
import sumo_bridge
from der_ros import cli
from der_ros.agent.dqn import DQNAgent, read_checkpoint
from der_ros.configuration import ConfigError, field_specs, from_dict
from sumo_bridge.scenario import ScenarioConfig

REPO = Path(__file__).resolve().parents[2]
CARTPOLE = REPO / "config" / "cartpole.yaml"
RING = REPO / "config" / "ring.yaml"


@pytest.mark.parametrize(
    ("content", "expect"),
    [
        (bytes(range(128, 256)), "not a text file: byte 0x80 at offset 0 is not UTF-8"),
        (b"", "the file is empty or holds only comments"),
        (b"# nothing but\n   # comments\n", "the file is empty or holds only comments"),
        (b"agent: {lr: .inf}\n", "[agent]: lr = inf, expected a finite number"),
        (b"replay: {lam: .nan}\n", "[replay]: lam = nan, expected a finite number"),
        (b"env: {id: Bogus-v9}\n", "env.id = 'Bogus-v9': Environment `Bogus` doesn't exist"),
        (b"agent: {batch_size: 256}\nreplay: {capacity: 100}\n", "batch_size = 256, expected <= replay.capacity (100)"),
        (b"replay: {capacity: 1.0e+12}\n", "replay buffer H1 (capacity=1000000000000"),
        (b"replay: {capacity: 1.0e+30}\n", "capacity = 1e+30, expected an integer that fits in 64 bits"),
    ],
    ids=["binary", "empty", "comments", "inf", "nan", "env-id", "batch>capacity", "capacity-1e12", "capacity-1e30"],
)
def test_a_bad_config_file_is_one_error_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, expect: str
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(content)
    run_dir = tmp_path / "run"
    assert cli.main(["train", "--config", str(bad), "--run-dir", str(run_dir), "--steps", "50"]) == 2
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("der train: configuration error: ") and expect in lines[0], err
    if b"id:" not in content and b"capacity: 1.0e+12" not in content:
        assert str(bad) in lines[0]  # the file is named (the env and the memory check name the key instead)
    assert not run_dir.exists()


def _config_dataclasses() -> list[type]:
    """Every config dataclass of the project (classes with param() fields), found by walking the packages."""
    found: dict[str, type] = {}
    for pkg in (der_ros, sumo_bridge):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            module = importlib.import_module(info.name)
            for _, cls in inspect.getmembers(module, inspect.isclass):
                if dataclasses.is_dataclass(cls) and cls.__module__ == module.__name__ and any(
                    "help" in f.metadata for f in dataclasses.fields(cls)):
                    found[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return list(found.values())


def test_every_float_field_of_every_config_must_be_finite() -> None:
    classes = _config_dataclasses()
    names = {c.__name__ for c in classes}
    assert {"DQNConfig", "ReplayConfig", "EnvConfig", "TrainConfig", "ScenarioConfig", "ObservationConfig",
            "RecorderConfig", "BridgeNodeConfig", "AgentNodeConfig"} <= names, names
    checked = 0
    for cls in classes:
        for spec in field_specs(cls):
            if spec.type is not float or spec.allow_inf:
                continue
            for bad in (float("inf"), float("-inf"), float("nan")):
                with pytest.raises(ConfigError, match=rf"{spec.name} = -?(inf|nan), expected a finite number"):
                    from_dict(cls, {spec.name: bad}, source=cls.__name__)
            checked += 1
    assert checked >= 30  # every float field of the project's configs (35 today), not a handful
    with pytest.raises(ConfigError, match=r"urban_depart_pos\[1\] = inf, expected a finite number"):
        from_dict(ScenarioConfig, {"urban_depart_pos": [40.0, float("inf")]})  # float lists too


# ----------------------------------------------------------------------------- resume from der graph's agent
@pytest.fixture
def node_checkpoint(ros_graph, tmp_path: Path) -> Path:  # noqa: F811 - fixture from ros_harness
    """A checkpoint written by a real agent_node process after a few synthetic episodes."""
    from test_nodes_agent import AGENT_PARAMS, FakeBridge

    ckpt = tmp_path / "agent.pt"
    b = FakeBridge(ros_graph, {**AGENT_PARAMS, "checkpoint_out": str(ckpt)})
    for _ in range(4):
        b.run_episode()
    b.latest_metrics(lambda v: v.get("online/transitions", 0) >= 28, "transitions stored")
    assert b.proc.stop() == 0 and ckpt.is_file()
    return ckpt


@pytest.mark.ros
def test_der_train_resumes_the_learner_of_a_graph_agent_checkpoint(
    node_checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = read_checkpoint(node_checkpoint)["agent"]
    start = int(before["steps"])
    assert "runner" not in read_checkpoint(node_checkpoint)["extra"]  # what made `der train --resume` fail
    # without --config: one clear sentence, nothing written
    run_dir = tmp_path / "run"
    assert cli.main(["train", "--resume", str(node_checkpoint), "--run-dir", str(run_dir)]) == 2
    assert "holds no training config (der graph's agent node writes none); pass --config" in capsys.readouterr().err
    # an environment it was not trained for: refused, nothing written
    assert cli.main(["train", "--resume", str(node_checkpoint), "--config", str(CARTPOLE), "--run-dir",
                     str(run_dir)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "cannot continue this agent here: it was trained on observations of shape (29,) with 3 actions" in err
    assert "gives (4,) with 2" in err and not run_dir.exists()
    # the ring env: the same learner goes on for 20 steps
    steps = start + 20
    assert cli.main(["train", "--resume", str(node_checkpoint), "--config", str(RING), "--run-dir", str(run_dir),
                     "--steps", str(steps), "--set", "train.eval_interval=0", "--set", "train.final_eval_episodes=0",
                     "--set", "train.tensorboard=false", "--set", "train.progress=false"]) == 0  # fmt: skip
    after = DQNAgent.load(run_dir / "checkpoint.pt")
    assert after.steps == steps
    # same agent and replay state: the node's settings (not ring.yaml's) and its stored transitions come first
    assert after.cfg.batch_size == before["dqn_cfg"]["batch_size"] == 8
    assert after.replay_cfg.capacity == before["replay_cfg"]["capacity"] == 1000
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert saved["agent"]["batch_size"] == 8 and saved["replay"]["capacity"] == 1000
    stored = DQNAgent.from_state_dict(before).replay.state_dict()
    resumed = after.replay.state_dict()
    n = start  # every transition the node observed is in H1 (capacity 1000), in order
    assert n >= 28
    for key in ("h1/obs", "h1/next_obs", "h1/actions", "h1/rewards"):
        np.testing.assert_array_equal(resumed[key][:n], stored[key][:n])
    assert np.any(resumed["h1/obs"][n:steps] != 0)  # and the 20 ring steps were stored after them
