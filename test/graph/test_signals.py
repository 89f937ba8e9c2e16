"""SIGINT and SIGTERM stop every `der` process in order even when it was started in the background.

A non-interactive shell starts background jobs with SIGINT *ignored*, and Python keeps it ignored;
these tests start each process that way (``preexec_fn``) and check that SIGINT / SIGTERM still stop
it the orderly way (checkpoint, finalised bag, exit 130), because the handlers are installed explicitly.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_harness import ros_domain  # noqa: F401 - fixture
from test_graph_cli import bag_meta, reap, wait_for_states

from der_ros.agent.dqn import DQNAgent
from der_ros.bag.writer import FINALIZED_KEY
from der_ros.graph.supervisor import ros_environment

REPO = Path(__file__).resolve().parents[2]
CARTPOLE = REPO / "config" / "cartpole.yaml"


def _background_start() -> None:
    """What a non-interactive shell does to a job started with ``&``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start(argv: list[str]) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "der_ros.cli", *argv], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
                            preexec_fn=_background_start)  # fmt: skip


def wait_file(path: Path, proc: subprocess.Popen[str], timeout: float = 120.0, min_size: int = 1) -> None:
    deadline = time.monotonic() + timeout
    while not (path.is_file() and path.stat().st_size >= min_size):
        if proc.poll() is not None:
            pytest.fail(f"exited with {proc.returncode} before {path} appeared:\n{proc.stdout.read()}")
        if time.monotonic() > deadline:
            pytest.fail(f"{path} did not appear within {timeout} s")
        time.sleep(0.2)


@pytest.mark.ros
def test_der_graph_started_in_the_background_stops_on_sigint(ros_domain: int, tmp_path: Path) -> None:  # noqa: F811
    run_dir = tmp_path / "run"
    proc = start(["graph", "--run-dir", str(run_dir), "--domain-id", str(ros_domain), "--steps", "100000",
                  "--no-plots", "--eval-interval", "0", "--final-eval-episodes", "0"])  # fmt: skip
    try:
        wait_for_states(run_dir, proc, more_than=20)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=90)
    finally:
        reap(proc, run_dir)
    assert proc.returncode == 130, out
    assert bag_meta(run_dir / "bag")["custom_data"][FINALIZED_KEY] == "true"
    assert (run_dir / "agent.pt").is_file()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exit_codes"] == {"recorder_node": 0, "agent_node": 0, "safety_node": 0, "bridge_node": 0}


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_der_train_started_in_the_background_checkpoints_on_sigint_and_sigterm(tmp_path: Path, sig: int) -> None:
    run_dir = tmp_path / "run"
    proc = start(["train", "--config", str(CARTPOLE), "--replay", "uniform", "--steps", "1000000", "--run-dir",
                  str(run_dir), "--set", "agent.hidden_sizes=[32]", "--set", "train.log_interval=50",
                  "--set", "train.tensorboard=false", "--set", "train.eval_interval=0",
                  "--set", "train.final_eval_episodes=0"])  # fmt: skip
    try:
        wait_file(run_dir / "metrics.csv", proc, min_size=2000)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, out
    assert "Traceback" not in out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] and 0 < summary["steps"] < 1_000_000
    assert DQNAgent.load(run_dir / "checkpoint.pt").steps == summary["steps"]


@pytest.mark.slow
def test_a_table_started_in_the_background_stops_its_runs_on_sigint(tmp_path: Path) -> None:
    """The suite's workers ignore SIGINT while idle; a SIGINT sent to the parent alone is passed on to the
    running trainings, which write their checkpoints (a rerun continues them)."""
    out_dir = tmp_path / "runs"
    proc = start(["table1", "--config", str(CARTPOLE), "--seeds", "1", "--steps", "1000000", "--methods", "dqn",
                  "--jobs", "1", "--out", str(out_dir), "--results", str(tmp_path / "results"), "--no-baselines",
                  "--set", "agent.hidden_sizes=[32]", "--set", "train.log_interval=50",
                  "--set", "train.tensorboard=false", "--set", "train.eval_interval=0",
                  "--set", "train.final_eval_episodes=0"])  # fmt: skip
    run_dir = out_dir / "dqn" / "seed1000"
    try:
        wait_file(run_dir / "metrics.csv", proc, min_size=2000)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["interrupted"] and 0 < summary["steps"] < 1_000_000
    assert DQNAgent.load(run_dir / "checkpoint.pt").steps == summary["steps"]


@pytest.mark.ros
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_node_started_in_the_background_stops_cleanly(ros_domain: int, tmp_path: Path, sig: int) -> None:  # noqa: F811
    """The node executables install their flag-setting handlers explicitly (nodes/spin.py)."""
    ckpt = tmp_path / "agent.pt"
    log = tmp_path / "agent.log"
    argv = [sys.executable, "-m", "der_ros.nodes.agent_node", "--ros-args", "-p", f"checkpoint_out:={ckpt}",
            "-p", "warm_up:=false"]
    with open(log, "w") as fh:
        proc = subprocess.Popen(argv, cwd=REPO, env=ros_environment(ros_domain), stdout=fh, stderr=subprocess.STDOUT,
                                start_new_session=True, preexec_fn=_background_start)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while "agent ready" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "agent ready" in log.read_text(), log.read_text()
        proc.send_signal(sig)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert f"stopping ({signal.Signals(sig).name})" in log.read_text() and ckpt.is_file()
