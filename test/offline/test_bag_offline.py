"""Offline training from a bag: the replay holds exactly the exported transitions; training and evaluation run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from bag_helpers import record_env_bag

from der_ros.agent.config import DQNConfig
from der_ros.bag.reader import BagReader
from der_ros.cli import main as der_main
from der_ros.offline.bag_cli import bag_info
from der_ros.offline.export import build_transitions
from der_ros.offline.train_from_bags import fill_replay, make_agent, online_numbers, train_offline
from der_ros.replay.config import ReplayConfig


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("offline") / "bag"
    record_env_bag(path, episodes=10, seed=5, max_episode_steps=20, policy_seed=1)
    return path


@pytest.mark.parametrize("kind", ["uniform", "der"])
def test_replay_buffer_holds_the_exported_transitions(bag: Path, kind: str) -> None:
    tr = build_transitions(BagReader(bag))
    n = len(tr)
    assert n >= 20
    agent = make_agent(tr.obs.shape[1], 3, DQNConfig(batch_size=8), ReplayConfig(kind=kind, capacity=1000, lam=0.9), 0)
    fill_replay(agent.replay, tr)
    assert len(agent.replay) == n
    sd = agent.replay.state_dict()
    prefix = "h1" if kind == "der" else "data"
    assert np.array_equal(sd[f"{prefix}/obs"][:n], tr.obs)
    assert np.array_equal(sd[f"{prefix}/next_obs"][:n], tr.next_obs)
    assert np.array_equal(sd[f"{prefix}/actions"][:n], tr.actions)
    assert np.array_equal(sd[f"{prefix}/rewards"][:n], tr.rewards.astype(np.float32))
    assert np.array_equal(sd[f"{prefix}/terminated"][:n], tr.terminated)
    assert np.array_equal(sd[f"{prefix}/truncated"][:n], tr.truncated)


def test_offline_training_updates_the_network_and_der_promotes(bag: Path) -> None:
    tr = build_transitions(BagReader(bag))
    dqn = DQNConfig(batch_size=8, target_update_interval=10)
    res = train_offline(tr, dqn, ReplayConfig(kind="der", capacity=1000, lam=0.9), steps=40, seed=1)
    fresh = make_agent(tr.obs.shape[1], 3, dqn, ReplayConfig(kind="der", capacity=1000, lam=0.9), 1)
    changed = any(not torch.equal(a, b) for a, b in zip(res.agent.q_net.parameters(), fresh.q_net.parameters()))
    assert changed
    assert res.agent.grad_steps == 40 and res.agent.steps == 0  # no environment step was taken
    assert res.final_metrics["replay/h2_size"] > 0  # transitions used in updates moved to H2
    assert np.isfinite(res.final_metrics["losses/td_loss"])


@pytest.mark.slow
def test_cli_train_reports_offline_and_online_numbers(bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["bag", "train", str(bag), "--replay", "der", "--lam", "0.9", "--steps", "30", "--batch-size", "8",
            "--eval-episodes", "2", "--max-episode-steps", "10", "--json"]
    assert der_main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["transitions"] == len(build_transitions(BagReader(bag)))
    assert doc["gradient_steps"] == 30 and doc["replay"] == "der" and doc["lam"] == 0.9
    ev = doc["offline_eval"]
    assert ev["episodes"] == 2 and len(ev["returns"]) == 2
    assert set(ev["outcomes"]) <= {"success", "collision", "time_limit"}
    assert ev["success_rate"] + ev["collision_rate"] + ev["time_limit_rate"] == pytest.approx(1.0)
    online = doc["online_from_bags"]
    summary = bag_info(bag)["summary"]
    assert online == online_numbers([bag])
    assert online["episodes"] == summary["finished_episodes"] == 10
    assert online["mean_return"] == pytest.approx(summary["mean_return"])
    assert online["success_rate"] == pytest.approx(summary["success_rate"])
