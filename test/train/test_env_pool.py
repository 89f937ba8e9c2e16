"""``train.num_envs``: N env workers feeding one learner (der_ros/train/env_pool.py).

Pinned here: N = 1 is the loop of before (same episodes, losses and weights as a config without the
field); N = 2 is deterministic for a seed, learns from both workers, one gradient step per transition;
each worker acts as the pool's docstring says (epsilon of its global step, its RNG, the snapshot of its
round), stops at its snapshot horizon and never steps beyond the run; it resumes exactly (a finished half, and a Ctrl-C); a killed worker stops the run with an error naming
it and leaves no process behind; bad values are refused with one line naming the field."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import torch
from test_train import CARTPOLE, read_csv, small_overrides

from der_ros import cli
from der_ros.agent.dqn import DQNAgent, read_checkpoint
from der_ros.configuration import ConfigError
from der_ros.train.config import load_experiment_config
from der_ros.train.env_pool import LAG_ROUNDS, EnvPool, _act_rng, worker_seed
from der_ros.train.envs import obs_spec
from der_ros.train.eval_seeds import TRAINING_SEED_LIMIT
from der_ros.train.runner import train


def episodes(run: Path) -> list[tuple[str, ...]]:
    return [(r["episode"], r["step"], r["return"], r["length"]) for r in read_csv(run / "episodes.csv")]


def losses(run: Path) -> list[str]:
    return [r["value"] for r in read_csv(run / "metrics.csv") if r["name"] == "losses/td_loss"]


def same_weights(a: Path, b: Path) -> bool:
    x, y = DQNAgent.load(a / "checkpoint.pt"), DQNAgent.load(b / "checkpoint.pt")
    return all(torch.equal(p, q) for p, q in zip(x.q_net.parameters(), y.q_net.parameters()))


def run(tmp_path: Path, name: str, steps: int, **extra: object) -> Path:
    cfg = load_experiment_config(CARTPOLE, small_overrides(steps, **extra))
    assert train(cfg, run_dir=tmp_path / name).steps == steps
    return tmp_path / name


def live_children() -> list[psutil.Process]:
    """Child processes still running, but multiprocessing's resource tracker (one per parent, kept)."""
    return [p for p in psutil.Process().children(recursive=True) if p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE and "resource_tracker" not in " ".join(p.cmdline())]  # fmt: skip


@pytest.mark.parametrize("loop", [{"train.env_process": False}, {"train.env_process": True}], ids=["sequential", "worker"])
def test_one_env_is_the_loop_of_before(tmp_path: Path, loop: dict) -> None:
    default = run(tmp_path, "default", 400, **loop)
    one = run(tmp_path, "one", 400, **{"train.num_envs": 1}, **loop)
    assert load_experiment_config(CARTPOLE).train.num_envs == 1
    assert len(episodes(one)) > 10 and episodes(one) == episodes(default)
    assert losses(one) and losses(one) == losses(default)
    assert same_weights(one, default)


def test_two_envs_are_deterministic_and_learn_from_both(tmp_path: Path) -> None:
    a = run(tmp_path, "a", 600, **{"train.num_envs": 2})
    b = run(tmp_path, "b", 600, **{"train.num_envs": 2})
    one = run(tmp_path, "one", 600)
    assert len(episodes(a)) > 10 and episodes(a) == episodes(b)
    assert losses(a) and losses(a) == losses(b)
    assert same_weights(a, b)
    assert episodes(a) != episodes(one)  # two streams interleaved, not the one env's
    agent = DQNAgent.load(a / "checkpoint.pt")
    assert agent.steps == 600 and agent.grad_steps == 600 - agent.cfg.learning_starts  # one gradient step per decision
    # both workers' streams reach the replay: two different first observations (their seeds differ)
    state = agent.replay.state_dict()
    stored = state["obs"] if "obs" in state else state["h1/obs"]
    firsts = {tuple(np.asarray(stored[i]).round(6)) for i in (0, 1)}
    assert len(firsts) == 2


@pytest.mark.slow  # three N = 2 runs (~9 s): full suite only
def test_two_envs_resume_exactly(tmp_path: Path) -> None:
    """The pool's state (each worker's pickled CartPole, its observation, RNG, step count and the results
    not yet learnt, the behaviour snapshots) goes into the checkpoint; the resumed run is the full run."""
    full = run(tmp_path, "full", 500, **{"train.num_envs": 2})
    half_cfg = load_experiment_config(CARTPOLE, small_overrides(250, **{"train.num_envs": 2}))
    half = train(half_cfg, run_dir=tmp_path / "split")
    pool = read_checkpoint(half.checkpoint)["extra"]["runner"]["pool"]
    assert pool["num_envs"] == 2 and all(w["env"] is not None for w in pool["workers"])
    full_cfg = load_experiment_config(CARTPOLE, small_overrides(500, **{"train.num_envs": 2}))
    train(full_cfg, run_dir=tmp_path / "split", resume=half.checkpoint)
    assert len(episodes(full)) > 10 and episodes(tmp_path / "split") == episodes(full)
    assert losses(tmp_path / "split") == losses(full)
    assert same_weights(tmp_path / "split", full)


@pytest.mark.slow  # three N = 2 runs with checkpoints (~10 s): full suite only
def test_two_envs_ctrl_c_writes_a_checkpoint_that_resumes_exactly(tmp_path: Path) -> None:
    full = run(tmp_path, "full", 800, **{"train.num_envs": 2})
    cfg = load_experiment_config(CARTPOLE, small_overrides(800, **{"train.num_envs": 2}))

    def on_episode(episode: int, step: int, ret: float) -> None:
        if episode == 12:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C: the workers ignore it, the trainer stops at a step

    cut = train(cfg, run_dir=tmp_path / "cut", on_episode=on_episode)
    assert cut.interrupted and 0 < cut.steps < 800 and cut.checkpoint
    assert not live_children()
    train(cfg, run_dir=tmp_path / "cut", resume=cut.checkpoint)
    assert episodes(tmp_path / "cut") == episodes(full)
    assert same_weights(tmp_path / "cut", full)


def test_a_killed_worker_stops_the_run_with_an_error_naming_it(tmp_path: Path) -> None:
    cfg = load_experiment_config(CARTPOLE, small_overrides(5000, **{"train.num_envs": 2}))
    killed: list[int] = []

    def on_episode(episode: int, step: int, ret: float) -> None:
        if episode == 3 and not killed:
            workers = sorted(p.pid for p in live_children())
            assert len(workers) >= 2
            os.kill(workers[1], signal.SIGKILL)
            killed.append(workers[1])

    with pytest.raises(RuntimeError, match=r"env worker [01] of 2 \(pid \d+\).*died \(exit code -9\)"):
        train(cfg, run_dir=tmp_path / "run", on_episode=on_episode)
    assert killed
    assert not live_children()


@pytest.mark.parametrize("value", ["0", "-1", "65", "1000", "two"])
def test_bad_num_envs_is_refused_with_one_line_naming_it(tmp_path: Path, value: str, capsys) -> None:
    run_dir = tmp_path / "run"
    code = cli.main(["train", "--config", str(CARTPOLE), "--set", f"train.num_envs={value}", "--run-dir", str(run_dir)])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "num_envs = " in err and value in err, err
    assert not run_dir.exists()
    with pytest.raises(ConfigError, match="num_envs"):
        load_experiment_config(CARTPOLE, {"train.num_envs": 2, "train.env_process": False})


def test_worker_seeds_come_from_the_run_seed_and_stay_training_seeds() -> None:
    for run_seed in (0, 7, 999_999_999):
        seeds = [worker_seed(run_seed, j) for j in range(64)]
        assert seeds[0] == run_seed and len(set(seeds)) == 64
        assert all(0 <= s < TRAINING_SEED_LIMIT for s in seeds)
    assert [worker_seed(3, j) for j in range(4)] == [worker_seed(3, j) for j in range(4)]
    assert worker_seed(3, 1) != worker_seed(4, 1)


def paused_steps(pool: EnvPool) -> list[int]:
    """Each worker's step count, read by pausing it (every result it streamed before is then in)."""
    pool.quiesce()
    steps = [int(w.paused["launched"]) for w in pool.workers]  # type: ignore[index]
    pool.resume()
    return steps


def settle(pool: EnvPool, expected: list[int]) -> list[int]:
    """Step counts once the workers have reached ``expected`` (or a minute has passed), a moment later."""
    deadline = time.monotonic() + 60
    while paused_steps(pool) != expected and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)  # room to overshoot, if a worker would
    return paused_steps(pool)


def test_workers_act_as_specified_stop_at_their_horizon_and_at_the_runs_end() -> None:
    cfg = load_experiment_config(CARTPOLE, small_overrides(100))
    pool = EnvPool(cfg.env, 3, 2)
    try:
        shape, dtype = obs_spec(pool)
        agent = DQNAgent(shape, dtype, int(pool.action_space.n), cfg.agent, cfg.replay, seed=3)
        # nothing learnt: round 0's snapshot serves steps 0..LAG_ROUNDS, the next needs round 1
        pool.start(agent, total_steps=10_000)
        assert settle(pool, [LAG_ROUNDS + 1] * 2) == [LAG_ROUNDS + 1] * 2
        for w in pool.workers:  # the k-th action: epsilon of step 2k + j, the worker's RNG, round 0's net
            assert len(w.results) == LAG_ROUNDS + 1
            rng, greedy = _act_rng(3, w.index), 0
            for k, (obs, action, *_rest) in enumerate(w.results):
                eps = agent.epsilon_schedule.value(2 * k + w.index)
                if eps > 0.0 and rng.random() < eps:
                    assert action == int(rng.integers(agent.n_actions))
                else:
                    q = agent.q_net(torch.as_tensor(np.asarray(obs, dtype=np.float32)).unsqueeze(0))
                    assert action == int(q.argmax(1).item())
                    greedy += 1
            assert greedy > 0
        pool.learnt_one(agent)
        pool.learnt_one(agent)  # round 1 ends: one more step each
        assert settle(pool, [LAG_ROUNDS + 2] * 2) == [LAG_ROUNDS + 2] * 2
    finally:
        pool.close()
    pool = EnvPool(cfg.env, 3, 2)
    try:
        pool.start(agent, total_steps=7)  # transitions 0..6: worker 0's steps 0..3, worker 1's 0..2
        assert settle(pool, [4, 3]) == [4, 3]
        assert [len(w.results) for w in pool.workers] == [4, 3]
    finally:
        pool.close()
    assert not live_children()
