"""``der graph`` end to end: bridge + agent + recorder as processes, the bag, Ctrl-C, a dying node."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from PIL import Image
from ros_harness import *  # noqa: F403 - ros_domain fixture
from rosbags.rosbag2 import Reader

from der_ros.bag.writer import FINALIZED_KEY, jazzy_typestore, read_episode_summary

REPO = Path(__file__).resolve().parents[2]
TS = jazzy_typestore()


def der_graph(run_dir: Path, domain: int, *extra: str) -> subprocess.Popen:
    """``der graph`` as a process; no greedy evaluations unless the test asks (they cost SUMO time)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    if "--final-eval-episodes" not in extra:
        extra = (*extra, "--eval-interval", "0", "--final-eval-episodes", "0")
    return subprocess.Popen(
        [sys.executable, "-m", "der_ros.cli", "graph", "--run-dir", str(run_dir), "--domain-id", str(domain),
         "--grace", "20", *extra],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )


def reap(proc: subprocess.Popen, run_dir: Path) -> None:
    """Teardown: never leave a runner or a node behind."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    pids = run_dir / "pids.json"
    if pids.exists():
        for pid in json.loads(pids.read_text()).values():
            try:
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass


def wait_until(pred, timeout: float, what: str, proc: subprocess.Popen) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout
    while not pred():
        if proc.poll() is not None:
            pytest.fail(f"der graph exited with {proc.returncode} while waiting for {what}:\n{proc.stdout.read()}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.1)


def node_logs(run_dir: Path, tail: int = 6000) -> str:
    """Every node's log of a run (their tails), for an assertion's message: a failure says why."""
    logs = sorted((run_dir / "logs").glob("*.log")) if (run_dir / "logs").is_dir() else []
    return "".join(f"\n===== {p.name} =====\n{p.read_text(errors='replace')[-tail:]}" for p in logs) or "\n(no node logs)"


def bag_meta(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def counts(meta: dict) -> dict[str, int]:
    return {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}


def wait_for_states(run_dir: Path, proc: subprocess.Popen, more_than: int) -> None:
    """Until the running graph's bag holds more than ``more_than`` states (the graph is up and stepping)."""
    bag = run_dir / "bag"
    wait_until(lambda: (bag / "metadata.yaml").exists() and counts(bag_meta(bag)).get("/state", 0) > more_than, 120,
               "states in the bag", proc)  # fmt: skip


def test_graph_runs_steps_and_records_everything(ros_domain: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    steps = 60
    proc = der_graph(run_dir, ros_domain, "--steps", str(steps), "--seed", "3", "--eval-interval", "30",
                     "--eval-episodes", "2", "--final-eval-episodes", "3")
    try:
        out, _ = proc.communicate(timeout=200)
    finally:
        reap(proc, run_dir)
    logs = node_logs(run_dir)
    assert proc.returncode == 0, out + logs
    assert "der graph: finished" in out, out + logs

    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["ok"] and summary["exit_codes"] == {"recorder_node": 0, "agent_node": 0, "safety_node": 0, "bridge_node": 0}, logs
    assert summary["checkpoint"] and Path(summary["checkpoint"]).is_file()
    assert summary["plots"] and all(Path(p).is_file() for p in summary["plots"])
    params = yaml.safe_load((run_dir / "params.yaml").read_text())
    assert params["bridge_node"]["ros__parameters"]["max_steps"] == steps
    assert params["agent_node"]["ros__parameters"]["seed"] == 3
    # the agent is "ready" (and the bridge started) only once the recorder matched its command writer
    assert params["agent_node"]["ros__parameters"]["min_command_subscribers"] == 1
    agent_log = (run_dir / "logs" / "agent_node.log").read_text()
    assert re.search(r"agent ready", agent_log)
    # its command's subscriber (the safety node, started before it) matched: the gate did not time out
    assert "starting anyway" not in agent_log, logs

    bag = run_dir / "bag"
    meta = bag_meta(bag)
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    c = counts(meta)
    for topic in ("/state", "/reward", "/lane_change_cmd", "/episode", "/clock", "/safety/interventions"):
        assert c.get(topic, 0) > 0, f"{topic}: {c}{logs}"
    # the default graph runs the shield: every command the bridge got passed the safety node, which recorded it
    assert summary["safety"]["commands"] == c["/safety/interventions"] >= steps - 1, logs
    assert "safety interventions" in out
    # the recorder stopped last, so it holds every state the bridge published (bridge's own count)
    bridge_log = (run_dir / "logs" / "bridge_node.log").read_text()
    bridge = json.loads(re.search(r"bridge summary: (\{.*\})", bridge_log).group(1))
    assert c["/state"] == int(bridge["published_states"]) == c["/reward"], logs
    assert c["/lane_change_cmd"] >= int(bridge["commands/accepted"]) >= steps - 1, logs
    episodes = read_episode_summary(bag)
    ends = [e for e in episodes if e["event"] != "start"]
    assert len(ends) == summary["episodes"] > 0
    # the summary's outcome counts agree with the bridge's own counters
    for event in ("success", "collision", "time_limit"):
        assert summary["outcomes"][event] == int(bridge[f"events/{event}"]), event
    assert summary["steps"] == int(bridge["sim_steps"]) == steps

    # the greedy evaluations: the agent's policy snapshots (start, every 30 steps) and its final checkpoint,
    # on held-out seeds, in a second process; the summary ends with the final one
    evals = (run_dir / "evaluations.csv").read_text().splitlines()
    rows = [tuple(row.split(",")[:2]) for row in evals[1:]]
    assert rows[:2] == [("0", "2"), ("30", "2")] and rows[-1] == ("60", "3")
    assert set(rows[2:-1]) <= {("60", "2")}  # the snapshot at 60 races the end of the run
    final = json.loads((run_dir / "evaluation.json").read_text())
    assert len(final["episodes"]) == 3 and min(final["seeds"]) >= 1_000_000_000
    assert summary["evaluation"]["episodes"] == 3 and "greedy policy (3 held-out episodes)" in out
    assert f"success {final['summary']['success']:.1%}" in out

    # the scene markers were recorded with every state (and the road once), and the run ends with a GIF of
    # one greedy episode: the final evaluation's first (same checkpoint, same held-out seed), frame by frame
    assert c["/scene/vehicles"] == int(bridge["published_states"]) and c["/scene/road"] == 1
    greedy = summary["greedy_episode"]
    gif = run_dir / "plots" / "greedy_episode.gif"
    assert greedy["gif"] == str(gif) and f"  episode:    {gif} (greedy" in out
    assert out.index("  plots:") < out.index("  episode:") < out.index("  logs:")
    first = final["episodes"][0]
    assert (greedy["seed"], greedy["outcome"]) == (final["seeds"][0], first["outcome"])
    # the ring commits the rest of the horizon at a safe change (one decision in the evaluation); the film runs
    # the plain horizon instead: the same decisions, the ego seen driving on to the end
    scenario = params["bridge_node"]["ros__parameters"]
    assert scenario["scenario.commit_on_success"] is True
    horizon = int(scenario["scenario.max_episode_steps"])
    if first["outcome"] == "collision":  # at the change or later, inside the committed stretch
        assert first["length"] <= greedy["steps"] <= horizon
    else:
        assert greedy["steps"] == horizon >= first["length"]
    assert greedy["return"] == pytest.approx(first["ret"])
    with Image.open(gif) as im:
        assert im.n_frames == greedy["steps"] + 1

    with Reader(bag) as r:
        conns = [x for x in r.connections if x.topic == "/state"]
        stamps = []
        for conn, _t, data in r.messages(connections=conns):
            msg = TS.deserialize_cdr(data, conn.msgtype)
            stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)  # step keys t_k, in order


def test_a_bogus_safety_value_is_refused_before_anything_starts(ros_domain: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    for value in ("bogus", "sumo"):
        proc = der_graph(run_dir, ros_domain, "--steps", "5", "--safety", value)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 2, out
        lines = [line for line in out.splitlines() if line.strip()]
        assert len(lines) == 1 and "--safety" in lines[0] and value in lines[0], out
        assert not run_dir.exists()


def test_a_run_the_agent_never_answered_is_a_failure(ros_domain: int, tmp_path: Path) -> None:
    """Every node exits 0, yet no step was driven by the agent (here: a command timeout of 1 us, shorter than any
    answer can take): der graph says so in one line and exits 1 instead of reporting a finished run."""
    run_dir = tmp_path / "run"
    proc = der_graph(run_dir, ros_domain, "--steps", "15", "--no-plots", "-p", "bridge_node:command_timeout=0.000001")
    try:
        out, _ = proc.communicate(timeout=200)
    finally:
        reap(proc, run_dir)
    logs = node_logs(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exit_codes"] == {"recorder_node": 0, "agent_node": 0, "safety_node": 0, "bridge_node": 0}, out + logs
    assert summary["bridge"]["sim_steps"] == 15 and summary["bridge"]["commands/accepted"] == 0, out + logs
    assert proc.returncode == 1, out + logs
    assert not summary["ok"] and "the agent answered none of the bridge's 15 steps" in summary["outcome"]
    assert "der graph: FAILED: the agent answered none of the bridge's 15 steps" in out
    assert "der graph: finished" not in out


def test_free_run_graph_with_the_real_agent_learns_and_records(ros_domain: int, tmp_path: Path) -> None:
    """--free-run: the bridge steps on its timer (5x real time: a step every 0.1 s) and applies the
    agent's latest command; the real agent stores every step and learns."""
    run_dir = tmp_path / "run"
    steps = 80
    overrides = ["bridge_node:real_time_factor=5.0", "agent_node:agent.learning_starts=20", "agent_node:agent.batch_size=16"]
    proc = der_graph(run_dir, ros_domain, "--steps", str(steps), "--free-run", "--no-plots",
                     *(arg for o in overrides for arg in ("-p", o)))  # fmt: skip
    try:
        out, _ = proc.communicate(timeout=150)
    finally:
        reap(proc, run_dir)
    assert proc.returncode == 0, out
    params = yaml.safe_load((run_dir / "params.yaml").read_text())
    assert params["bridge_node"]["ros__parameters"]["mode"] == "free_run"
    bridge_log = (run_dir / "logs" / "bridge_node.log").read_text()
    bridge = json.loads(re.search(r"bridge summary: (\{.*\})", bridge_log).group(1))
    assert bridge["sim_steps"] == steps
    # the timer did not wait for the agent, and the agent's answers drove the simulation (how many steps it
    # answers in time on a 0.1 s timer depends on the machine's load: bench/graph.py measures throughput,
    # a test asserts no wall-clock share)
    assert 0 < bridge["commands/accepted"] <= steps, bridge
    metrics = json.loads((run_dir / "summary.json").read_text())["metrics"]
    assert metrics["online/transitions"] == steps  # one stored transition per bridge step
    assert metrics["online/learn_steps"] > 0
    meta = bag_meta(run_dir / "bag")
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    assert counts(meta)["/state"] == int(bridge["published_states"])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_ctrl_c_stops_cleanly_with_a_finalised_bag(ros_domain: int, tmp_path: Path, sig: int) -> None:
    run_dir = tmp_path / "run"
    proc = der_graph(run_dir, ros_domain, "--steps", "100000", "--no-plots")
    try:
        wait_for_states(run_dir, proc, more_than=20)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        reap(proc, run_dir)
    assert proc.returncode == 130, out
    meta = bag_meta(run_dir / "bag")
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    assert (run_dir / "agent.pt").is_file()  # the agent saved on its way out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exit_codes"] == {"recorder_node": 0, "agent_node": 0, "safety_node": 0, "bridge_node": 0}


def test_a_dying_node_fails_the_run_and_is_named(ros_domain: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    proc = der_graph(run_dir, ros_domain, "--steps", "100000", "--no-plots")
    try:
        wait_for_states(run_dir, proc, more_than=5)
        agent_pid = json.loads((run_dir / "pids.json").read_text())["agent_node"]
        os.kill(agent_pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=60)
    finally:
        reap(proc, run_dir)
    assert proc.returncode == 1, out
    assert f"agent_node died (exit {-signal.SIGKILL})" in out
    assert "last lines of agent_node" in out
    last_line = (run_dir / "logs" / "agent_node.log").read_text().splitlines()[-1]
    assert last_line in out  # the tail of its log
    # the others were stopped cleanly: the recorder finalised the bag
    assert bag_meta(run_dir / "bag")["custom_data"][FINALIZED_KEY] == "true"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exit_codes"]["recorder_node"] == 0 and summary["exit_codes"]["bridge_node"] == 0


def _running(pid: int) -> bool:
    """True while ``pid`` runs (a zombie left for init to reap counts as gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return fields[0] not in ("Z", "X")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only")
def test_nodes_stop_when_the_runner_is_sigkilled(ros_domain: int, tmp_path: Path) -> None:
    """kill -9 of `der graph` cannot stop anybody in order; the nodes still get SIGTERM and shut down."""
    run_dir = tmp_path / "run"
    proc = der_graph(run_dir, ros_domain, "--steps", "100000", "--no-plots")
    try:
        wait_for_states(run_dir, proc, more_than=5)
        pids = json.loads((run_dir / "pids.json").read_text())
        assert set(pids) == {"recorder_node", "agent_node", "safety_node", "bridge_node"}  # the shield is on by default
        assert all(_running(pid) for pid in pids.values())
        os.kill(proc.pid, signal.SIGKILL)  # the runner only: the nodes are in sessions of their own
        proc.wait(timeout=10)
        deadline = time.monotonic() + 60
        while any(_running(pid) for pid in pids.values()) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = {name: pid for name, pid in pids.items() if _running(pid)}
    finally:
        reap(proc, run_dir)
    assert not left, f"nodes still running 60 s after the runner was killed: {left}"
    # they stopped through their SIGTERM path: the bag is finalised and the agent saved
    assert bag_meta(run_dir / "bag")["custom_data"][FINALIZED_KEY] == "true"
    assert (run_dir / "agent.pt").is_file()
    assert "SIGTERM" in (run_dir / "logs" / "agent_node.log").read_text()


def test_composed_mode_runs_the_same_graph_in_one_process(ros_domain: int, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    proc = der_graph(run_dir, ros_domain, "--steps", "40", "--composed", "--no-plots")
    try:
        out, _ = proc.communicate(timeout=150)
    finally:
        reap(proc, run_dir)
    assert proc.returncode == 0, out
    assert set(json.loads((run_dir / "pids.json").read_text())) == {"graph"}
    log_text = (run_dir / "logs" / "graph.log").read_text()
    bridge = json.loads(re.search(r"bridge summary: (\{.*\})", log_text).group(1))
    assert bridge["sim_steps"] == 40
    meta = bag_meta(run_dir / "bag")
    assert meta["custom_data"][FINALIZED_KEY] == "true"
    c = counts(meta)
    assert c["/state"] == int(bridge["published_states"]) and c["/lane_change_cmd"] >= 40
    assert (run_dir / "agent.pt").is_file()


def test_the_greedy_film_runs_the_plain_horizon():
    """A commit ends the episode at the lane change; the GIF's env turns it off (same decisions and
    return, the ego seen driving on) and leaves every other scenario field alone."""
    from der_ros.graph.greedy_episode import watchable_env_config
    from der_ros.graph.snapshot_evaluation import scenario_env_config

    bridge = {"scenario.network": "ring", "scenario.commit_on_success": True, "scenario.max_episode_steps": 30}
    env_cfg = scenario_env_config(bridge)
    watched = watchable_env_config(env_cfg)
    assert env_cfg.kwargs["scenario"]["commit_on_success"] is True  # not modified in place
    assert watched.kwargs["scenario"] == {"commit_on_success": False, "max_episode_steps": 30}
    assert watched.id == env_cfg.id
    plain = scenario_env_config({"scenario.network": "ring"})
    assert watchable_env_config(plain) is plain
