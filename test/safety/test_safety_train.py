"""The shield in process: the gymnasium wrapper, ``der train`` storing the applied action, ``der table3 --shield``."""

from __future__ import annotations

import collections
import json
from pathlib import Path

import numpy as np
import pytest

from der_ros import cli
from der_ros.agent.dqn import DQNAgent
from der_ros.configuration import from_dict
from der_ros.safety.observation_mask import ObservationMask
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE, evaluation_seeds
from der_ros.train.runner import train
from sumo_bridge.observation import ObservationConfig
from sumo_bridge.policies import immediate_policy

REPO = Path(__file__).resolve().parents[2]
RING = "der_ros/LaneChangeRing-v0"


def immediate(obs: np.ndarray, infos: list[dict]) -> list[int]:
    return [immediate_policy(i["points"]) for i in infos]


@pytest.mark.parametrize("kind", ["rss", "sumo"])
def test_wrapper_vetoes_the_immediate_policy_into_zero_caused_collisions(kind: str) -> None:
    """Always "change now" on the ring: unshielded it causes collisions, behind the shield none."""
    n = 20
    seeds = evaluation_seeds(n, TUNING_EVAL_SEED_BASE)
    outcomes = {}
    for k in ("none", kind):
        env = make_env_from_config(from_dict(EnvConfig, {"id": RING, "safety": {"kind": k}}), 0)
        try:
            eps = run_episodes(immediate, [env], seeds, n)
        finally:
            env.close()
        outcomes[k] = (collections.Counter("caused" if e.caused else e.outcome for e in eps),
                       sum(e.interventions for e in eps))  # fmt: skip
    assert outcomes["none"][0]["caused"] > 0 and outcomes["none"][1] == 0
    assert outcomes[kind][0]["caused"] == 0
    assert outcomes[kind][1] > 0 and outcomes[kind][0]["success"] > 0


def test_wrapper_info_names_proposal_and_applied_action() -> None:
    env = make_env_from_config(from_dict(EnvConfig, {"id": RING, "safety": {"kind": "rss"}}), 0)
    try:
        obs, info = env.reset(seed=TUNING_EVAL_SEED_BASE)
        assert info["action_mask"][0] and info["interventions"] == 0
        seen_veto = False
        for _ in range(50):
            mask = info["action_mask"]
            obs, _, term, trunc, info = env.step(1)  # always "left" (the target lane)
            assert info["proposed_action"] == 1
            assert info["applied_action"] == (1 if mask[1] else 0)
            assert info["intervened"] == (not mask[1])
            seen_veto |= info["intervened"]
            if term or trunc:
                break
        assert seen_veto
    finally:
        env.close()


def _stored_actions_allowed(run_dir: Path, obs_cfg: ObservationConfig) -> float:
    agent = DQNAgent.load(run_dir / "checkpoint.pt")
    n = len(agent.replay)
    obs, actions = agent.replay.storage.obs[:n], agent.replay.storage.actions[:n]
    from der_ros.safety.config import SafetyConfig

    allowed = ObservationMask(SafetyConfig(kind="rss"), obs_cfg)(obs)
    return float(allowed[np.arange(n), actions.astype(int)].mean())


def test_training_stores_the_applied_action(tmp_path: Path) -> None:
    """Random exploration proposes unsafe changes; behind the shield the replay holds only allowed ones."""
    ring = REPO / "config" / "ring.yaml"
    base = {"replay.kind": "uniform", "train.total_steps": 150, "agent.learning_starts": 1000, "agent.hidden_sizes": [16],
            "train.eval_interval": 0, "train.final_eval_episodes": 0, "train.tensorboard": False,
            "train.env_process": False}  # fmt: skip
    obs_cfg = ObservationConfig(**{k: v for k, v in load_experiment_config(ring).env.kwargs["scenario"]["observation"].items()})
    fractions = {}
    for kind in ("none", "rss"):
        cfg = load_experiment_config(ring, {**base, "env.safety.kind": kind})
        train(cfg, run_dir=tmp_path / kind)
        fractions[kind] = _stored_actions_allowed(tmp_path / kind, obs_cfg)
    assert fractions["none"] < 0.9  # epsilon 1: many unsafe proposals were stored as they were
    assert fractions["rss"] > 0.99  # (float32 rounding of a gap may flip a verdict at the boundary)


@pytest.mark.slow
def test_table3_shield_rows_and_eval_episodes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, results = tmp_path / "runs", tmp_path / "results"
    argv = ["table3", "--networks", "ring", "--methods", "dqn", "--seeds", "1", "--steps", "80", "--shield", "rss"]
    argv += ["--jobs", "2", "--out", str(out), "--results", str(results)]
    argv += ["--set", "agent.learning_starts=40", "--set", "agent.hidden_sizes=[16]", "--set", "train.tensorboard=false"]
    argv += ["--set", "train.eval_interval=0", "--set", "train.final_eval_episodes=4"]
    assert cli.main(argv) == 0
    table = json.loads((results / "table3.json").read_text())["ring"]
    assert {"dqn", "dqn+shield", "immediate+shield", "gap_acceptance+shield"} <= set(table)
    assert table["dqn"]["eval_episodes"] == [4.0] and table["dqn+shield"]["eval_episodes"] == [4.0]
    assert table["dqn"]["eval_interventions"] == [0.0]
    assert table["immediate+shield"]["eval_collision"] == 0.0 and table["immediate+shield"]["eval_interventions"] > 0
    cfg = json.loads(json.dumps(load_experiment_config(out / "ring" / "dqn+shield" / "seed1000" / "config.yaml").to_dict()))
    assert cfg["env"]["safety"]["kind"] == "rss"
    assert "DQN + shield" in (results / "table3.md").read_text()
    capsys.readouterr()
