"""``train.env_process``: the environment in a worker process, the gradient step overlapping its step.

Pinned here: the order (act, then the update, then the step's transition: the ROS graph's order)
against a reference loop written out in process; determinism and exact resume; errors that come
back from the worker; a worker that dies; no worker left behind."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from test_train import CARTPOLE, read_csv, small_overrides

from der_ros import cli
from der_ros.agent.dqn import DQNAgent, read_checkpoint
from der_ros.configuration import ConfigError
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.env_process import EnvProcess
from der_ros.train.envs import make_env_from_config
from der_ros.train.runner import train

OVERLAP = {"train.env_process": True}


def episodes(run: Path) -> list[tuple[str, ...]]:
    return [(r["episode"], r["step"], r["return"], r["length"]) for r in read_csv(run / "episodes.csv")]


def test_the_order_is_act_then_update_then_the_steps_transition(tmp_path: Path) -> None:
    """The runner with the env in a worker equals, episode for episode and weight for weight, this loop in
    process: a = act(s); learn() on the replay without (s, a, ...); step; observe. The sequential loop
    (observe before learn) gives another run from the same seed: the option is not a no-op."""
    steps = 400
    cfg = load_experiment_config(CARTPOLE, small_overrides(steps, **{"replay.kind": "der", "replay.lam": 0.5},
                                                           **OVERLAP))
    run = train(cfg, run_dir=tmp_path / "worker")
    assert run.steps == steps

    env = make_env_from_config(cfg.env, cfg.train.seed)
    agent = DQNAgent(env.observation_space.shape, env.observation_space.dtype, int(env.action_space.n), cfg.agent,
                     cfg.replay, seed=cfg.train.seed, device=cfg.train.device)  # fmt: skip
    obs, _ = env.reset(seed=cfg.train.seed)
    returns, ret = [], 0.0
    while agent.steps < steps:
        action = agent.act(obs)
        agent.learn()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        agent.observe(obs, action, float(reward), next_obs, bool(terminated), bool(truncated))
        ret += float(reward)
        if terminated or truncated:
            returns.append(ret)
            ret = 0.0
            next_obs, _ = env.reset()
        obs = next_obs
    env.close()
    assert len(returns) > 10
    assert [float(e[2]) for e in episodes(tmp_path / "worker")] == pytest.approx(returns, abs=1e-6)
    saved = DQNAgent.load(tmp_path / "worker" / "checkpoint.pt")
    assert all(torch.equal(x, y) for x, y in zip(saved.q_net.parameters(), agent.q_net.parameters()))

    sequential = load_experiment_config(CARTPOLE, small_overrides(steps, **{"replay.kind": "der", "replay.lam": 0.5}))
    train(sequential, run_dir=tmp_path / "sequential")
    a = DQNAgent.load(tmp_path / "sequential" / "checkpoint.pt")
    assert not all(torch.equal(x, y) for x, y in zip(a.q_net.parameters(), saved.q_net.parameters()))


def test_resume_with_the_env_in_a_worker_continues_exactly(tmp_path: Path) -> None:
    """CartPole's env state is pickled out of the worker into the checkpoint and loaded back into it."""
    full_cfg = load_experiment_config(CARTPOLE, small_overrides(500, **OVERLAP))
    train(full_cfg, run_dir=tmp_path / "full")
    half = train(load_experiment_config(CARTPOLE, small_overrides(250, **OVERLAP)), run_dir=tmp_path / "split")
    assert read_checkpoint(half.checkpoint)["extra"]["env"] is not None  # the worker's env, pickled
    train(full_cfg, run_dir=tmp_path / "split", resume=half.checkpoint)
    assert len(episodes(tmp_path / "full")) > 5
    assert episodes(tmp_path / "split") == episodes(tmp_path / "full")


def test_a_bad_env_in_the_worker_is_a_config_error_and_writes_nothing(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    code = cli.main(["train", "--config", str(CARTPOLE), "--set", "env.id=NoSuchEnv-v0", "--set",
                     "train.env_process=true", "--run-dir", str(run_dir)])  # fmt: skip
    assert code == 2
    assert "NoSuchEnv-v0" in capsys.readouterr().err
    assert not run_dir.exists()


def test_errors_in_the_worker_come_back_and_a_dead_worker_is_named() -> None:
    env = EnvProcess(EnvConfig(id="CartPole-v1"), seed=0)
    try:
        assert isinstance(env.observation_space, gym.spaces.Box) and env.action_space.n == 2
        env.reset(seed=1)
        env.step_async(7)  # not an action of CartPole: the env raises in the worker
        with pytest.raises(RuntimeError, match="in the environment process: AssertionError"):
            env.step_wait()
        env.step_async(1)  # the worker serves on after an error
        obs, reward, terminated, truncated, info, reset = env.step_wait()
        assert obs.shape == (4,) and reward == 1.0 and reset is None
        with pytest.raises(RuntimeError, match="step_async"):
            env.step_wait()
        os.kill(env.pid, signal.SIGKILL)
        time.sleep(0.5)
        with pytest.raises((RuntimeError, BrokenPipeError), match="died|Broken pipe"):
            env.step_async(0)
            env.step_wait()
    finally:
        env.close()
    assert not env._proc.is_alive()


def test_an_episode_end_brings_the_reset_along_and_close_leaves_no_process() -> None:
    env = EnvProcess(EnvConfig(id="CartPole-v1"), seed=0)
    pid = env.pid
    env.reset(seed=3)
    ends = 0
    for _ in range(200):
        env.step_async(0)  # always left: episodes of ~10 steps
        obs, _r, terminated, truncated, _info, reset = env.step_wait()
        assert (reset is not None) == (terminated or truncated)
        if reset is not None:
            ends += 1
            assert reset[0].shape == (4,) and isinstance(reset[1], dict)
    assert ends >= 5
    env.close()
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_env_process_is_refused_for_a_bad_type() -> None:
    with pytest.raises(ConfigError, match="env_process"):
        load_experiment_config(CARTPOLE, {"train.env_process": "sometimes"})
