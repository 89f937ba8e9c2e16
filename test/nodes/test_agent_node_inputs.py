"""The agent node under poisoned inputs, time jumps and a diverging learner (real agent_node processes;
the test's probe plays the bridge, as in test_nodes_agent)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from ros_harness import ros_domain, ros_graph, wait_for  # noqa: F401 - fixtures
from std_srvs.srv import Trigger
from test_nodes_agent import AGENT_PARAMS, EPISODE, STEP_NS, FakeBridge

from der_ros import contract as ct
from der_ros.agent.dqn import read_checkpoint
from der_ros.nodes import msg_conversions as mc
from sumo_bridge.observation import field_index

pytestmark = pytest.mark.ros


def finite_checkpoint(path: Path) -> bool:
    """Every float in the networks, the optimizer and the replay of a checkpoint is finite."""
    agent = read_checkpoint(path)["agent"]
    tensors = [*agent["q_net"].values(), *agent["target_net"].values()]
    replay = agent["replay"]
    tensors += list(replay["tensors"].values()) if replay.get("__packed__") else []
    return all(bool(torch.isfinite(t.float()).all()) for t in tensors if torch.is_tensor(t) and t.is_floating_point())


def test_non_finite_and_out_of_range_inputs_are_rejected_counted_and_never_stored(ros_graph, tmp_path):  # noqa: F811
    ckpt = tmp_path / "agent.pt"
    b = FakeBridge(ros_graph, {**AGENT_PARAMS, "checkpoint_out": str(ckpt)})
    b.run_episode()
    # well-formed messages carrying poison, at the stamp of the next step
    stamp = b.k * STEP_NS
    for value in (float("nan"), float("inf"), 1e300):
        pts = b.points()
        pts[0, field_index("speed")] = value
        b.pub_state.publish(mc.points_to_cloud(pts, stamp))
    for reward in (1e300, -1e30, float("inf")):
        msg = mc.make_reward(stamp, 0.0, False, False)
        msg.vector.x = reward
        b.pub_reward.publish(msg)
    for _ in range(4):  # learning starts after 8 steps: gradient steps run on what was stored
        assert len(b.run_episode()) == EPISODE - 1
    m = b.latest_metrics(lambda v: v.get("agent/bad_state", 0) >= 3 and v.get("agent/bad_reward", 0) >= 3
                         and v.get("online/transitions", 0) >= 5 * (EPISODE - 1), "the rejections to be counted")
    assert m["agent/bad_state"] == 3 and m["agent/bad_reward"] == 3
    assert m["online/transitions"] == 5 * (EPISODE - 1) and m["online/gaps"] == 0
    assert m["online/learn_steps"] > 0 and np.isfinite(m["losses/td_loss"])
    assert b.proc.stop() == 0  # alive until asked to stop, then saves
    assert finite_checkpoint(ckpt)
    rejected = [x for x in b.proc.output().splitlines() if "rejected" in x]
    assert rejected and any("expected a finite number" in x for x in rejected)


def test_a_restarted_bridge_is_followed_as_a_new_stream(ros_graph):  # noqa: F811
    b = FakeBridge(ros_graph, AGENT_PARAMS)
    for _ in range(2):
        b.run_episode()
    b.k = 0  # the bridge restarts: sim time from 0 again
    b.step(first=True)  # step 0 of the new stream: one step back could be a stale copy, so it is not answered
    cmds = b.run_episode()[1:]  # from its second step on, every state is answered
    assert len(cmds) == EPISODE - 2
    m = b.latest_metrics(lambda v: v.get("online/stream_jumps", 0) >= 1, "the stream jump to be counted")
    assert m["online/stream_jumps"] == 1
    wait_for(lambda: "stream_jumps +1" in b.proc.output(), 20, what="the jump in the log", procs=[b.proc])
    assert "the stream jumped" in b.proc.output()


def test_one_absurd_future_stamp_cannot_mute_the_agent(ros_graph):  # noqa: F811
    b = FakeBridge(ros_graph, AGENT_PARAMS)
    b.run_episode()
    far = 10**18  # ~31 years of sim time
    b.pub_reward.publish(mc.make_reward(far, 5.0, False, False))
    b.pub_state.publish(mc.points_to_cloud(b.points(), far))
    for _ in range(3):
        assert len(b.run_episode()) == EPISODE - 1  # every later state is still answered
    assert not any(ct.stamp_to_ns(c.header.stamp) == far for c in list(b.cmds))
    m = b.latest_metrics(lambda v: v.get("online/stale_state", 0) >= 1, "the future pair to be counted as stale")
    assert m["online/stale_state"] == 1 and m["online/stale_reward"] == 1 and m["online/gaps"] == 0


def test_drops_are_logged_at_a_bounded_rate(ros_graph):  # noqa: F811
    b = FakeBridge(ros_graph, AGENT_PARAMS)
    b.run_episode()
    t0 = time.monotonic()
    for _ in range(5):  # 200 stale copies of step 0, in bursts the reward queue (depth 50) holds
        for _ in range(40):
            b.pub_reward.publish(mc.make_reward(0, 0.0, False, False))
        time.sleep(0.3)
    b.run_episode()
    elapsed = time.monotonic() - t0
    wait_for(lambda: "stale_reward +" in b.proc.output(), 20, what="a drop report", procs=[b.proc])
    assert b.proc.stop() == 0
    out = b.proc.output()
    assert "'stale_reward': 200," in out.splitlines()[-1]  # every drop counted (the final counters)
    lines = [x for x in out.splitlines() if "dropped since the last report" in x]
    assert lines and all("stale_reward +" in x for x in lines)
    assert len(lines) <= 2 + elapsed / 5.0  # at most one line per 5 s, whatever the rate of drops
    assert sum(int(n) for x in lines for n in re.findall(r"stale_reward \+(\d+)", x)) <= 200


def diverge(b: FakeBridge) -> None:
    """Rewards of 1e30 (accepted: max_abs_reward is raised to 3e38) overflow the squared TD loss."""
    for _ in range(5):
        if b.proc.poll() is not None or "the learner diverged" in b.proc.output():
            return
        for i in range(EPISODE):
            stamp = b.k * STEP_NS
            b.pub_reward.publish(mc.make_reward(stamp, 0.0 if i == 0 else 1e30, i == EPISODE - 1, False))
            b.pub_state.publish(mc.points_to_cloud(b.points(), stamp))
            b.k += 1
            if i < EPISODE - 1:  # a lockstep bridge waits for the answer (none after a terminal step)
                wait_for(lambda s=stamp: any(ct.stamp_to_ns(c.header.stamp) >= s for c in list(b.cmds))
                         or b.proc.poll() is not None or "the learner diverged" in b.proc.output(), 20,
                         what="the agent to answer or diverge", procs=[])


DIVERGING = {**AGENT_PARAMS, "checkpoint_every": 0, "max_abs_reward": 3e38}


def test_a_diverged_learner_keeps_the_last_good_checkpoint(ros_graph, tmp_path):  # noqa: F811
    ckpt = tmp_path / "agent.pt"
    b = FakeBridge(ros_graph, {**DIVERGING, "checkpoint_out": str(ckpt)})
    for _ in range(3):
        b.run_episode()
    b.latest_metrics(lambda v: v.get("online/learn_steps", 0) >= 1, "learning to start")
    res = b.probe.call(Trigger, "/agent/save_checkpoint", Trigger.Request())
    assert res.success and finite_checkpoint(ckpt)
    good = ckpt.read_bytes()
    good_steps = int(read_checkpoint(ckpt)["agent"]["steps"])
    (res,) = b.probe.set_parameters("agent_node", {"agent.lr": 1e30})  # issue 45: no longer a valid value
    assert not res.successful and "agent.lr out of range" in res.reason and "Max: 1.0" in res.reason
    diverge(b)
    assert b.proc.wait(timeout=30) == 1
    out = b.proc.output()
    assert "Traceback" not in out
    errors = [x for x in out.splitlines() if "ERROR" in x]
    assert len(errors) == 1 and "the learner diverged" in errors[0], out
    diverged = tmp_path / "agent.diverged.pt"
    assert f"kept the last good checkpoint {ckpt} (step {good_steps})" in errors[0]
    assert f"the state at divergence is in {diverged}" in errors[0]
    assert ckpt.read_bytes() == good and diverged.is_file()  # never overwritten, the bad state beside it


def test_ctrl_c_while_a_diverged_agent_stops_still_exits_1(ros_graph, tmp_path):  # noqa: F811
    """Issue 45: a Ctrl-C during the post-divergence drain made the agent exit -2 (SIGINT) instead of 1."""
    import signal

    b = FakeBridge(ros_graph, {**DIVERGING, "checkpoint_out": str(tmp_path / "agent.pt")})
    for _ in range(2):
        b.run_episode()
    b.latest_metrics(lambda v: v.get("online/learn_steps", 0) >= 1, "learning to start")
    diverge(b)
    wait_for(lambda: "the learner diverged" in b.proc.output() or b.proc.poll() is not None, 30,
             what="the divergence", procs=[])
    while b.proc.poll() is None:  # Ctrl-C (again and again) while it drains, saves and shuts down
        b.proc.signal(signal.SIGINT)
        time.sleep(0.01)
    assert b.proc.wait(timeout=30) == 1, b.proc.output()[-3000:]


def test_the_save_service_says_why_a_diverged_learner_was_not_saved(tmp_path):
    """Issue 45: after a divergence the service answered 'checkpoint_out is empty: nowhere to save'."""
    from der_ros.nodes.agent_node import save_reply

    good = tmp_path / "agent.pt"
    assert save_reply(good, str(good), diverged=False) == (True, str(good))
    assert save_reply(None, "", diverged=False) == (False, "checkpoint_out is empty: nowhere to save")
    ok, message = save_reply(None, str(good), diverged=True)
    assert not ok and message.startswith("not saved: the learner diverged") and "nowhere" not in message
    assert f"no good checkpoint was written ({good})" in message
    good.write_bytes(b"x")
    assert save_reply(None, str(good), diverged=True)[1].endswith(f"{good} keeps the last good checkpoint")
