"""Training runner, `der train` CLI, config validation, env factory and learning on CartPole."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

from der_ros import cli
from der_ros.agent.config import DQNConfig
from der_ros.agent.dqn import DQNAgent
from der_ros.configuration import ConfigError
from der_ros.replay.config import ReplayConfig
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env
from der_ros.train.runner import train

REPO = Path(__file__).resolve().parents[2]
CARTPOLE = REPO / "config" / "cartpole.yaml"


# ----------------------------------------------------------------------------- learning
def heldout_batch(n: int = 256) -> tuple[torch.Tensor, ...]:
    """Transitions of a random policy on CartPole (fixed seed), never given to the agent."""
    env = gym.make("CartPole-v1")
    env.action_space.seed(123)
    obs, _ = env.reset(seed=123)
    rows = []
    while len(rows) < n:
        a = int(env.action_space.sample())
        nxt, r, term, trunc, _ = env.step(a)
        rows.append((obs, a, r, nxt, term))
        obs = nxt
        if term or trunc:
            obs, _ = env.reset()
    o, a, r, nx, t = zip(*rows)
    return (
        torch.from_numpy(np.asarray(o, dtype=np.float32)),
        torch.from_numpy(np.asarray(a, dtype=np.int64)),
        torch.from_numpy(np.asarray(r, dtype=np.float32)),
        torch.from_numpy(np.asarray(nx, dtype=np.float32)),
        torch.from_numpy(np.asarray(t, dtype=bool)),
    )


def heldout_td_loss(agent: DQNAgent, batch: tuple[torch.Tensor, ...]) -> float:
    obs, act, rew, nxt, term = batch
    with torch.no_grad():
        y = agent.td_targets(rew, nxt, term)
        q = agent.q_net(obs).gather(1, act[:, None])[:, 0]
        return float((y - q).square().mean())


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["uniform", "per", "der"])
def test_each_replay_kind_learns_on_cartpole(kind: str) -> None:
    """A few hundred CartPole steps: the TD loss on a held-out batch, against the frozen target
    network, must fall to a fraction of its initial value for every replay kind."""
    dqn = DQNConfig(
        gamma=0.98,
        batch_size=64,
        hidden_sizes=[64],
        learning_starts=100,
        target_update_interval=10**6,  # frozen target: a regression problem with a fixed answer
        epsilon_decay_steps=200,
        lr=1e-3,
    )
    rep = ReplayConfig(kind=kind, capacity=5000, lam=0.5, h2_capacity=640, beta_steps=400)
    agent = DQNAgent((4,), np.float32, 2, dqn, rep, seed=0)
    batch = heldout_batch()
    before = heldout_td_loss(agent, batch)
    env = make_env("CartPole-v1", seed=0)
    obs, _ = env.reset(seed=0)
    metrics: dict[str, float] = {}
    for _ in range(500):
        a = agent.act(obs)
        nxt, r, term, trunc, _ = env.step(a)
        agent.observe(obs, a, float(r), nxt, term, trunc)
        metrics = agent.learn() or metrics
        obs = nxt if not (term or trunc) else env.reset()[0]
    after = heldout_td_loss(agent, batch)
    assert after < 0.2 * before, (before, after)
    assert agent.grad_steps == 400
    stats = agent.replay.stats()
    if kind == "der":  # update_priorities reached DER: transitions were promoted to H2 and sampled
        assert stats["replay/h2_size"] > 0 and stats["replay/h2_fraction"] > 0
        assert stats["replay/h2_weight_mean"] >= 1.0
    assert not any(k.startswith("replay/") for k in metrics)  # the gauges come from replay.stats() when logged
    if kind == "per":
        assert stats["replay/per_beta"] > rep.beta0


# ----------------------------------------------------------------------------- runner
def small_overrides(steps: int, **extra: object) -> dict[str, object]:
    return {
        "agent.hidden_sizes": [64],
        "agent.batch_size": 32,
        "agent.learning_starts": 100,
        "agent.epsilon_decay_steps": 300,
        "agent.target_update_interval": 50,
        "replay.capacity": 2000,
        "replay.h2_capacity": 320,
        "train.total_steps": steps,
        "train.log_interval": 50,
        "train.tensorboard": False,
        "train.progress": False,
        "train.final_eval_episodes": 0,
        "train.eval_interval": 0,
        **extra,
    }


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_runner_resume_continues_exactly(tmp_path: Path) -> None:
    cfg_full = load_experiment_config(CARTPOLE, small_overrides(600, **{"replay.kind": "der", "replay.lam": 0.5}))
    full = train(cfg_full, run_dir=tmp_path / "full")
    cfg_half = load_experiment_config(CARTPOLE, small_overrides(300, **{"replay.kind": "der", "replay.lam": 0.5}))
    half = train(cfg_half, run_dir=tmp_path / "split")
    assert half.steps == 300 and half.checkpoint
    resumed = train(cfg_full, run_dir=tmp_path / "split", resume=half.checkpoint)
    assert resumed.steps == full.steps == 600

    def episodes(run: str) -> list[tuple[str, ...]]:
        return [(r["episode"], r["step"], r["return"], r["length"]) for r in read_csv(tmp_path / run / "episodes.csv")]

    def losses(run: str) -> list[tuple[str, ...]]:
        rows = read_csv(tmp_path / run / "metrics.csv")
        return [(r["step"], r["name"], r["value"]) for r in rows if r["name"].startswith(("losses/", "replay/"))]

    assert len(episodes("full")) > 10
    assert episodes("split") == episodes("full")
    assert losses("split") == losses("full")
    a = DQNAgent.load(tmp_path / "full" / "checkpoint.pt")
    b = DQNAgent.load(tmp_path / "split" / "checkpoint.pt")
    assert all(torch.equal(x, y) for x, y in zip(a.q_net.parameters(), b.q_net.parameters()))


def test_der_train_cli_writes_run_directory(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    extra = {"train.tensorboard": True, "train.eval_interval": 150, "train.eval_episodes": 2,
             "train.final_eval_episodes": 3}
    sets = [f"{k}={json.dumps(v)}" for k, v in small_overrides(300, **extra).items()]
    argv = ["train", "--config", str(CARTPOLE), "--replay", "der", "--lam", "0.9", "--seed", "3"]
    argv += ["--run-dir", str(run_dir), "--agent-lr", "0.001"]
    for s in sets:
        argv += ["--set", s]
    assert cli.main(argv) == 0
    resolved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert resolved["replay"]["kind"] == "der" and resolved["replay"]["lam"] == 0.9
    assert resolved["train"]["seed"] == 3 and resolved["agent"]["lr"] == 0.001
    assert resolved["agent"]["gamma"] == 0.98  # from the file
    names = {r["name"] for r in read_csv(run_dir / "metrics.csv")}
    for name in (
        "charts/steps_per_s",
        "charts/epsilon",
        "losses/td_loss",
        "losses/abs_td_error",
        "losses/q_values",
        "replay/h2_fraction",
        "replay/h2_weight_mean",
        "eval/mean_return",
        "eval/success",
        "charts/episodic_return",
        "charts/episodic_length",
    ):
        assert name in names
    evals = read_csv(run_dir / "evaluations.csv")
    assert [(int(r["step"]), int(r["episodes"])) for r in evals] == [(0, 2), (150, 2), (300, 3)]
    assert all(float(r["mean_return"]) >= 8 for r in evals)
    episodes = read_csv(run_dir / "episodes.csv")
    assert episodes and all(float(e["return"]) == float(e["length"]) for e in episodes)  # CartPole: +1 per step
    assert int(episodes[-1]["step"]) <= 300
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["steps"] == 300 and summary["episodes"] == len(episodes) and not summary["interrupted"]
    agent = DQNAgent.load(run_dir / "checkpoint.pt")
    assert agent.steps == 300 and agent.replay_cfg.kind == "der"


@pytest.mark.slow
def test_a_burst_of_ctrl_c_is_one_stop_and_the_checkpoint_is_written(tmp_path: Path) -> None:
    """The same Ctrl-C can arrive more than once (a terminal signals the whole group, a suite's backend
    forwards it to its runs): signals within 2 s of the first do not abort the interrupted checkpoint
    and summary (a 2-million-transition replay makes that save take a while)."""
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "der_ros.cli", "train", "--config", str(CARTPOLE), "--replay", "uniform"]
    cmd += ["--steps", "1000000", "--run-dir", str(run_dir), "--set", "agent.hidden_sizes=[32]"]
    cmd += ["--set", "agent.learning_starts=100", "--set", "train.log_interval=50", "--set", "train.tensorboard=false"]
    cmd += ["--set", "replay.capacity=2000000"]
    proc = subprocess.Popen(cmd, env=dict(os.environ, OMP_NUM_THREADS="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not ((run_dir / "metrics.csv").is_file() and (run_dir / "metrics.csv").stat().st_size > 2000):
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.2)
        for _ in range(12):  # up to 1.2 s of repeated SIGINTs, over the loop's end and the save
            if proc.poll() is not None or (run_dir / "summary.json").exists():
                break
            os.killpg(proc.pid, signal.SIGINT)
            time.sleep(0.1)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # 130 from the CLI; a signal of the burst that comes after everything was written may end the exiting
    # process by SIGINT (-2): nothing is lost either way
    assert proc.returncode in (130, -signal.SIGINT), err
    assert "Traceback" not in err and "already stopping" in err
    assert err.index("already stopping") < err.index("interrupted at step")  # repeats came during the save
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] and DQNAgent.load(run_dir / "checkpoint.pt").steps == summary["steps"]


@pytest.mark.slow
@pytest.mark.parametrize("env_process", [False, True], ids=["in-process", "env-process"])
def test_ctrl_c_saves_checkpoint_and_resume_finishes(tmp_path: Path, env_process: bool) -> None:
    """Ctrl-C as a terminal sends it: SIGINT to the whole process group (with the env in a worker, the
    worker too: it leaves the stop to the trainer and exits when closed; nothing of the group survives)."""
    run_dir = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "der_ros.cli", "train", "--config", str(CARTPOLE), "--replay", "uniform"]
    cmd += ["--steps", "1000000", "--run-dir", str(run_dir), "--set", "agent.hidden_sizes=[32]"]
    cmd += ["--set", "agent.learning_starts=100", "--set", "train.log_interval=50", "--set", "train.tensorboard=false"]
    cmd += ["--set", f"train.env_process={str(env_process).lower()}"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            metrics = run_dir / "metrics.csv"
            if metrics.is_file() and metrics.stat().st_size > 2000:
                break
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    deadline = time.monotonic() + 10
    while True:  # the worker (and the evaluator) exit with the trainer
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "a process of the run outlived it"
        time.sleep(0.1)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] and 0 < summary["steps"] < 1_000_000
    stopped = summary["steps"]
    assert DQNAgent.load(run_dir / "checkpoint.pt").steps == stopped
    # resume with the stored config, 100 more steps
    assert cli.main(["train", "--resume", str(run_dir / "checkpoint.pt"), "--steps", str(stopped + 100)]) == 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["steps"] == stopped + 100 and not summary["interrupted"]
    steps = [int(r["step"]) for r in read_csv(run_dir / "episodes.csv")]
    assert steps == sorted(steps) and steps[-1] > stopped


# ----------------------------------------------------------------------------- config errors
@pytest.mark.parametrize(
    ("section", "key", "value", "expect"),
    [
        ("agent", "lrr", 0.001, "unknown key 'lrr'"),
        ("agent", "batch_size", "big", "batch_size = 'big', expected an integer"),
        ("agent", "gamma", 1.5, "gamma = 1.5, expected"),
        ("replay", "lam", -0.2, "lam = -0.2, expected"),
        ("train", "device", "tpu", "device = 'tpu', expected one of"),
        ("envs", None, None, "unknown section 'envs'"),
    ],
)
def test_invalid_config_fails_before_training_naming_file_key_value(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], section: str, key: str | None, value: object, expect: str
) -> None:
    data = yaml.safe_load(CARTPOLE.read_text())
    if key is None:
        data[section] = {"id": "CartPole-v1"}
    else:
        data[section][key] = value
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    run_dir = tmp_path / "run"
    assert cli.main(["train", "--config", str(bad), "--run-dir", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and expect in err
    if key is not None:
        assert f"[{section}]" in err
    assert not run_dir.exists()  # failed before anything started


def test_invalid_override_names_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["train", "--config", str(CARTPOLE), "--lam", "1.5", "--run-dir", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "command line" in err and "lam = 1.5" in err


def test_overrides_reach_inside_mapping_valued_keys() -> None:
    """``--set env.kwargs.scenario.time_aware=true`` sets one key deep inside env.kwargs and keeps its siblings;
    the file's own mapping is not modified; a path through a non-mapping is an error naming the key."""
    ring = REPO / "config" / "ring.yaml"
    base = load_experiment_config(ring)
    cfg = load_experiment_config(ring, ["env.kwargs.scenario.time_aware=true",
                                        "env.kwargs.scenario.observation.speed_scale=10"])
    scenario = cfg.env.kwargs["scenario"]
    assert scenario["time_aware"] is True and scenario["observation"]["speed_scale"] == 10
    assert scenario["observation"]["neighbour_range"] == base.env.kwargs["scenario"]["observation"]["neighbour_range"]
    assert {k: v for k, v in scenario.items() if k not in ("time_aware", "observation")} == {
        k: v for k, v in base.env.kwargs["scenario"].items() if k != "observation"}
    assert "time_aware" not in load_experiment_config(ring).env.kwargs["scenario"]
    with pytest.raises(ConfigError, match="scenario.max_episode_steps"):
        load_experiment_config(ring, {"env.kwargs.scenario.max_episode_steps.x": 1})


# ----------------------------------------------------------------------------- environments
def test_atari_episodic_life_continues_the_game() -> None:
    env = make_env("ALE/Breakout-v5", seed=0, terminal_on_life_loss=True)
    try:
        env.reset(seed=0)
        lives0 = env.unwrapped.ale.lives()
        for _ in range(2000):
            _, r, term, trunc, info = env.step(env.action_space.sample())
            assert r in (0.0, 1.0)  # clipped
            if term or trunc:
                break
        assert term and info.get("life_lost") and "episode" not in info
        env.reset()
        assert env.unwrapped.ale.lives() == lives0 - 1  # same game, one life fewer
    finally:
        env.close()


def test_make_env_kinds() -> None:
    cp = make_env("CartPole-v1", seed=0)
    assert cp.observation_space.shape == (4,)
    cp.close()
    with pytest.raises(gym.error.Error):
        make_env("NoSuchEnv-v0", seed=0)


@pytest.mark.slow
@pytest.mark.parametrize("env_process", [False, True], ids=["in-process", "env-process"])
def test_runner_on_sumo_ring_env(tmp_path: Path, env_process: bool) -> None:
    """`der_ros/...` ids go through make_env (importing sumo_bridge); a short DER run on the ring, with the
    simulation in the trainer's process or in a worker (then three processes: trainer, env, evaluator)."""
    cfg = load_experiment_config(
        None,
        small_overrides(
            150,
            **{
                "env.id": "der_ros/LaneChangeRing-v0",
                "agent.learning_starts": 50,
                "train.eval_interval": 60,
                "train.eval_episodes": 1,
                "train.final_eval_episodes": 2,
                "train.env_process": env_process,
            },
        ),
    )
    summary = train(cfg, run_dir=tmp_path / "ring")
    assert summary.steps == 150
    names = {r["name"] for r in read_csv(tmp_path / "ring" / "metrics.csv")}
    assert {"losses/td_loss", "replay/h2_size"} <= names
    # evaluated in a second process (one libsumo simulation per process) while training went on
    evals = read_csv(tmp_path / "ring" / "evaluations.csv")
    assert [(int(r["step"]), int(r["episodes"])) for r in evals] == [(0, 1), (60, 1), (120, 1), (150, 2)]
    final = json.loads((tmp_path / "ring" / "evaluation.json").read_text())
    assert final["step"] == 150 and {e["outcome"] for e in final["episodes"]} <= {"success", "collision", "time_limit"}
    agent = DQNAgent.load(tmp_path / "ring" / "checkpoint.pt")
    assert agent.n_actions == 3 and len(agent.obs_shape) == 1 and agent.replay_cfg.kind == "der"
