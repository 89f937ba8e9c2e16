"""``train.env_process``: the environment in a worker process, the gradient step overlapping its step.

Pinned here: the same run as the sequential loop, bit for bit (the replay completes the step's
transition when a batch first reads it); determinism and exact resume; errors that come
back from the worker; a worker that dies; no worker left behind."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_train import CARTPOLE, read_csv, small_overrides

from der_ros import cli
from der_ros.agent.dqn import DQNAgent, read_checkpoint
from der_ros.configuration import ConfigError
from der_ros.replay.config import ReplayConfig
from der_ros.replay.factory import make_replay
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.env_process import EnvProcess
from der_ros.train.runner import train

OVERLAP = {"train.env_process": True}


def episodes(run: Path) -> list[tuple[str, ...]]:
    return [(r["episode"], r["step"], r["return"], r["length"]) for r in read_csv(run / "episodes.csv")]


@pytest.mark.slow
@pytest.mark.parametrize("replay", [{"replay.kind": "uniform"}, {"replay.kind": "per"},
                                    {"replay.kind": "der", "replay.lam": 0.5}], ids=["uniform", "per", "der"])
def test_the_worker_loop_equals_the_sequential_loop_bit_for_bit(tmp_path: Path, replay: dict) -> None:
    """The gradient step runs while the worker simulates, on a replay that already holds the step's
    (s, a) and completes the transition when a batch first reads it: episodes, metrics and every weight
    equal those of the sequential loop (act, step, observe, learn) from the same seed."""
    steps = 400
    runs = {}
    for name, extra in (("worker", OVERLAP), ("sequential", {"train.env_process": False})):
        cfg = load_experiment_config(CARTPOLE, small_overrides(steps, **replay, **extra))
        assert train(cfg, run_dir=tmp_path / name).steps == steps
        runs[name] = DQNAgent.load(tmp_path / name / "checkpoint.pt")
    assert len(episodes(tmp_path / "worker")) > 10
    assert episodes(tmp_path / "worker") == episodes(tmp_path / "sequential")
    losses = [[r["value"] for r in read_csv(tmp_path / n / "metrics.csv") if r["name"] == "losses/td_loss"]
              for n in runs]  # fmt: skip
    assert losses[0] and losses[0] == losses[1]
    a, b = runs["worker"], runs["sequential"]
    assert all(torch.equal(x, y) for x, y in zip(a.q_net.parameters(), b.q_net.parameters()))
    sa, sb = a.replay.state_dict(), b.replay.state_dict()
    assert sa.keys() == sb.keys() and all(np.array_equal(sa[k], sb[k]) for k in sa)


def test_a_batch_that_holds_the_deferred_transition_completes_it_first() -> None:
    """ReplayBuffer.add_deferred: complete() runs when a gather reads the slot (then the batch holds the
    real values), not when the batch misses it; resolve_deferred and saving the state complete it too."""
    rng = np.random.default_rng(0)
    misses = 0
    calls: list[int] = []

    def complete() -> tuple:
        calls.append(1)
        return 7.0, np.full(3, 9.0, np.float32), True, False

    for kind in ("uniform", "per", "der"):
        cfg = ReplayConfig(kind=kind, capacity=64, h2_capacity=32, lam=0.5)
        buf = make_replay(cfg, (3,), np.float32, batch_size=4, seed=0)
        for k in range(4):
            buf.add(np.full(3, k, np.float32), 0, 1.0, np.full(3, k + 0.5, np.float32), False, False)
        calls.clear()
        buf.add_deferred(np.full(3, 4.0, np.float32), 1, complete)
        for _ in range(200):  # five transitions, batches of 4: some hold the new one, some do not
            batch = buf.sample(4)
            if (batch.obs[:, 0] == 4.0).any():
                break
            assert calls == [], kind  # a batch without it does not wait for it
            misses += 1
        assert calls == [1], kind
        row = int(np.flatnonzero(batch.obs[:, 0] == 4.0)[0])
        assert batch.rewards[row] == 7.0 and batch.next_obs[row, 0] == 9.0 and batch.terminated[row], kind
        assert batch.actions[row] == 1
        buf.update_priorities(batch.indices, rng.normal(size=4))
        buf.add_deferred(np.full(3, 5.0, np.float32), 2, complete)
        buf.state_dict()  # saving reads every slot
        assert calls == [1, 1], kind
        buf.add_deferred(np.full(3, 6.0, np.float32), 2, complete)
        buf.resolve_deferred()
        buf.resolve_deferred()  # nothing waits any more
        assert calls == [1, 1, 1], kind
    assert misses > 0  # the check that a missing batch does not wait ran


@pytest.mark.slow
def test_resume_with_the_env_in_a_worker_continues_exactly(tmp_path: Path) -> None:
    """CartPole's env state is pickled out of the worker into the checkpoint and loaded back into it."""
    full_cfg = load_experiment_config(CARTPOLE, small_overrides(500, **OVERLAP))
    train(full_cfg, run_dir=tmp_path / "full")
    half = train(load_experiment_config(CARTPOLE, small_overrides(250, **OVERLAP)), run_dir=tmp_path / "split")
    assert read_checkpoint(half.checkpoint)["extra"]["env"] is not None  # the worker's env, pickled
    train(full_cfg, run_dir=tmp_path / "split", resume=half.checkpoint)
    assert len(episodes(tmp_path / "full")) > 5
    assert episodes(tmp_path / "split") == episodes(tmp_path / "full")


@pytest.mark.slow
def test_a_bad_env_in_the_worker_is_a_config_error_and_writes_nothing(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    code = cli.main(["train", "--config", str(CARTPOLE), "--set", "env.id=NoSuchEnv-v0", "--set",
                     "train.env_process=true", "--run-dir", str(run_dir)])  # fmt: skip
    assert code == 2
    assert "NoSuchEnv-v0" in capsys.readouterr().err
    assert not run_dir.exists()


@pytest.mark.slow
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


@pytest.mark.slow
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


def test_auto_puts_only_the_sumo_envs_in_a_worker_and_only_with_two_cpus_per_run(monkeypatch) -> None:
    from der_ros.experiments.backends import local
    from der_ros.train.env_process import CPUS_PER_RUN_ENV, MIN_STEPS_FOR_WORKER, cpus_per_run, use_env_process

    ring, cartpole = "der_ros/LaneChangeRing-v0", "CartPole-v1"
    monkeypatch.setenv(CPUS_PER_RUN_ENV, "2")
    assert use_env_process(None, ring) and not use_env_process(None, cartpole)
    assert not use_env_process(False, ring) and use_env_process(True, cartpole)  # as set wins
    assert not use_env_process(None, ring, evaluator_process=True)  # evaluations beside it need a third CPU
    assert not use_env_process(None, ring, total_steps=MIN_STEPS_FOR_WORKER - 1)  # the start would not pay back
    monkeypatch.setenv(CPUS_PER_RUN_ENV, "3")
    assert use_env_process(None, ring, evaluator_process=True)
    monkeypatch.setenv(CPUS_PER_RUN_ENV, "1")
    assert not use_env_process(None, ring)
    monkeypatch.setenv(CPUS_PER_RUN_ENV, "two")
    with pytest.raises(ConfigError, match="DER_CPUS_PER_RUN.*'two'"):
        use_env_process(None, ring)
    monkeypatch.delenv(CPUS_PER_RUN_ENV)
    assert cpus_per_run() == len(os.sched_getaffinity(0))
    # the local backend's workers get their share: 2 parallel runs on 2 cores = 1 CPU each
    monkeypatch.setattr(local.signal, "signal", lambda *a: None)  # (the initializer ignores Ctrl-C in a worker)
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)
    local._worker_init(2 / 2)  # (monkeypatch restores the variable: it was set through it above)
    assert os.environ[CPUS_PER_RUN_ENV] == "1"
