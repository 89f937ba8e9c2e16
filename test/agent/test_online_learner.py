"""Unit tests of the agent node's ROS-free core: joining by stamp, transitions, episodes, pause."""

import numpy as np
import pytest

from der_ros.agent.online import OnlineLearner

S = 100_000_000


class FakeAgent:
    """Records calls; acts by a fixed cycle so tests know which action answered which state."""

    def __init__(self, actions=(1, 2, 0)):
        self.actions = list(actions)
        self.i = 0
        self.observed = []
        self.acted = []
        self.learn_calls = 0

    def act(self, obs, explore=True):
        a = self.actions[self.i % len(self.actions)]
        self.i += 1
        self.acted.append((float(obs[0]), explore))
        return a

    def observe(self, obs, action, reward, next_obs, terminated, truncated):
        self.observed.append((float(obs[0]), action, reward, float(next_obs[0]), terminated, truncated))

    def learn(self):
        self.learn_calls += 1
        return {"losses/td_loss": 1.0}


def obs(v):
    return np.array([v, 0.0], dtype=np.float32)


def step(learner, k, reward, term=False, trunc=False, reward_first=True):
    if reward_first:
        out = learner.on_reward(k * S, reward, term, trunc)
        assert out == []
        return learner.on_state(k * S, obs(k))
    out = learner.on_state(k * S, obs(k))
    assert out == []
    return learner.on_reward(k * S, reward, term, trunc)


def test_transitions_follow_the_contract():
    agent = FakeAgent()
    L = OnlineLearner(agent)
    d0 = step(L, 0, 0.0)
    assert [d.action for d in d0] == [1] and d0[0].stamp_ns == 0 and not d0[0].stored
    d1 = step(L, 1, 0.5, reward_first=False)  # arrival order across topics does not matter
    assert d1[0].action == 2 and d1[0].stored
    d2 = step(L, 2, -1.0, term=True)
    assert d2[0].action is None  # no command for a terminal state
    ep = d2[0].episode
    assert ep is not None and ep.ret == pytest.approx(-0.5) and ep.length == 2 and ep.terminated
    assert ep.lane_change_cmds == 2  # actions 1 and 2 were lane-change commands
    # (s_k, a_k, r_{k+1}, s_{k+1}, terminated_{k+1}, truncated_{k+1})
    assert agent.observed == [
        (0.0, 1, 0.5, 1.0, False, False),
        (1.0, 2, -1.0, 2.0, True, False),
    ]
    # next episode: first state forms no transition with the terminal one
    d3 = step(L, 3, 0.0)
    assert d3[0].action == 0 and not d3[0].stored
    d4 = step(L, 4, 1.0, trunc=True)
    assert agent.observed[-1] == (3.0, 0, 1.0, 4.0, False, True)
    assert d4[0].episode.truncated and not d4[0].episode.terminated and d4[0].episode.index == 1
    assert d4[0].episode.lane_change_cmds == 0
    assert L.counters["transitions"] == 3


def test_duplicates_and_stale_messages_are_counted_not_used():
    agent = FakeAgent()
    L = OnlineLearner(agent)
    step(L, 0, 0.0)
    assert L.on_state(0, obs(9)) == []  # re-delivery of a completed stamp
    assert L.counters["stale_state"] == 1
    L.on_reward(S, 0.1, False, False)
    assert L.on_reward(S, 0.7, False, False) == []
    assert L.counters["duplicate_reward"] == 1
    d = L.on_state(S, obs(1))
    assert d[0].action is not None
    assert agent.observed == [(0.0, 1, pytest.approx(0.1), 1.0, False, False)]  # first copy wins
    assert L.on_reward(0, 5.0, False, False) == []
    assert L.counters["stale_reward"] == 1


def test_lagging_topic_steps_are_joined_in_stamp_order():
    agent = FakeAgent()
    L = OnlineLearner(agent)
    step(L, 0, 0.0)
    # the state topic runs two steps ahead of the reward topic (DDS orders topics separately)
    assert L.on_state(S, obs(1)) == []
    assert L.on_state(2 * S, obs(2)) == []
    d1 = L.on_reward(S, 1.0, False, False)
    d2 = L.on_reward(2 * S, 2.0, False, False)
    assert [x.stamp_ns for x in d1 + d2] == [S, 2 * S]
    assert [(o[0], o[2], o[3]) for o in agent.observed] == [(0.0, 1.0, 1.0), (1.0, 2.0, 2.0)]
    assert L.counters["gaps"] == 0


def test_known_step_size_detects_a_step_lost_on_both_topics():
    agent = FakeAgent()
    L = OnlineLearner(agent, step_ns=S)
    step(L, 0, 0.0)
    d = step(L, 2, 2.0)  # step 1 never arrived at all
    assert not d[0].stored and L.counters["gaps"] == 1 and agent.observed == []
    step(L, 3, 3.0)
    assert [(o[0], o[3]) for o in agent.observed] == [(2.0, 3.0)]


def test_lost_message_is_a_gap_and_never_joins_wrong_states():
    agent = FakeAgent()
    L = OnlineLearner(agent)
    step(L, 0, 0.0)
    L.on_state(S, obs(1))  # the reward of step 1 is lost
    d = step(L, 2, 2.0)
    assert d[0].action is not None and not d[0].stored
    assert L.counters["gaps"] == 1
    assert agent.observed == []  # (s_0, a_0) was not joined to s_2
    step(L, 3, 3.0)
    assert agent.observed == [(2.0, agent.observed[0][1], 3.0, 3.0, False, False)]


def test_buffer_is_bounded():
    L = OnlineLearner(FakeAgent(), max_buffered=4)
    for k in range(10):
        L.on_state(k * S, obs(k))  # rewards never arrive
    assert L.buffered == 4 and L.counters["evicted"] == 6


def test_pause_acts_greedily_and_does_not_learn():
    agent = FakeAgent()
    L = OnlineLearner(agent)
    step(L, 0, 0.0)
    L.set_paused(True)
    step(L, 1, 1.0)
    step(L, 2, 1.0)
    assert agent.observed == []  # the pending training step was dropped, evaluation steps not stored
    assert agent.acted[-1][1] is False and agent.acted[0][1] is True
    assert L.learn() == {} and agent.learn_calls == 0
    d = step(L, 3, 1.0, term=True)
    assert d[0].episode.evaluation is False  # episode started in training mode
    step(L, 4, 0.0)
    d = step(L, 5, 2.0, term=True)
    assert d[0].episode.evaluation and "eval/episodic_return" in d[0].episode.metrics()
    L.set_paused(False)
    step(L, 6, 0.0)
    step(L, 7, 1.0)
    assert len(agent.observed) == 1
    assert L.learn() == {"losses/td_loss": 1.0} and L.counters["learn_steps"] == 1


def test_encode_is_applied_to_state_payloads():
    agent = FakeAgent()
    L = OnlineLearner(agent, encode=lambda p: np.asarray(p, dtype=np.float32) * 10)
    step(L, 0, 0.0)
    step(L, 1, 0.0)
    assert agent.observed[0][0] == 0.0 and agent.observed[0][3] == 10.0


def test_with_real_dqn_agent_buffers_fill_and_learning_starts():
    torch = pytest.importorskip("torch")
    torch.set_num_threads(1)
    from der_ros.agent.config import DQNConfig
    from der_ros.agent.dqn import DQNAgent
    from der_ros.replay.config import ReplayConfig

    cfg = DQNConfig(batch_size=4, learning_starts=8, hidden_sizes=[16])
    agent = DQNAgent((2,), np.float32, 3, cfg, ReplayConfig(), seed=1)
    L = OnlineLearner(agent)
    rng = np.random.default_rng(0)
    got = {}
    for k in range(40):
        term = k % 10 == 9
        L.on_reward(k * S, float(rng.normal()) if k % 10 else 0.0, term, False)
        for d in L.on_state(k * S, rng.normal(size=2).astype(np.float32)):
            assert d.action is None or 0 <= d.action < 3
        got.update(L.learn())
    # 4 episodes x 9 transitions, all in H1; the default promote_mode 'copy' keeps them there and
    # adds copies of the high-|TD| ones to H2, so the whole buffer holds at least as many
    assert agent.replay.h1_size == L.counters["transitions"] == 36
    assert 36 <= len(agent.replay) == agent.replay.h1_size + agent.replay.h2_size
    assert "losses/td_loss" in got and np.isfinite(got["losses/td_loss"])


def test_applied_action_reported_by_the_bridge_replaces_ours():
    agent = FakeAgent(actions=(2,))
    L = OnlineLearner(agent)
    L.on_reward(0, 0.0, False, False)  # episode start: nothing applied yet
    L.on_state(0, obs(0))
    # our answer (2) missed the timeout: the bridge applied its default 0 and says so
    L.on_reward(S, 1.0, False, False, applied_action=0)
    L.on_state(S, obs(1))
    L.on_reward(2 * S, 1.0, False, False, applied_action=2)  # this one was on time
    L.on_state(2 * S, obs(2))
    assert [o[1] for o in agent.observed] == [0, 2]
    assert L.counters["overridden_actions"] == 1


# -- poisoned inputs and time jumps (issue 12) ----------------------------------------------------------
@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (lambda L: L.on_state(0, np.array([np.nan, 0.0])), r"state point\[0\] = nan"),
        (lambda L: L.on_state(0, np.array([0.0, np.inf])), r"state point\[1\] = inf"),
        (lambda L: L.on_state(0, np.array([1e300, 0.0])), r"state point\[0\] = 1e\+300, expected a finite number within float32"),
        (lambda L: L.on_reward(0, float("nan"), False, False), r"reward = nan"),
        (lambda L: L.on_reward(0, 1e300, False, False), r"reward = 1e\+300"),
        (lambda L: L.on_reward(0, -1e30, False, False), r"reward = -1e\+30, expected a finite number with \|reward\| <= 1e\+06"),
    ],
    ids=["nan-state", "inf-state", "huge-state", "nan-reward", "1e300-reward", "1e30-reward"],
)
def test_poisoned_inputs_are_rejected_before_anything_is_buffered(bad, match):
    agent = FakeAgent()
    L = OnlineLearner(agent)
    with pytest.raises(ValueError, match=match):
        bad(L)
    assert L.buffered == 0 and L.counters["states"] == 0 and L.counters["rewards"] == 0
    for k in range(3):  # the stream goes on, and nothing poisoned reached the agent
        step(L, k, 1.0)
    assert len(agent.observed) == 2 and all(np.isfinite(o[2]) for o in agent.observed)


def test_a_non_finite_observation_from_the_encoder_is_rejected():
    L = OnlineLearner(FakeAgent(), encode=lambda p: np.where(np.asarray(p) > 1e9, np.inf, p))
    with pytest.raises(ValueError, match=r"observation\[0\] = inf"):
        L.on_state(0, np.array([1e10, 0.0]))


def test_a_restarted_bridge_is_a_new_stream_and_nothing_wrong_is_stored():
    """Sim time starts again at 0: the second consecutive step of the new stream is answered; no transition
    joins the old stream's last state to the new one."""
    agent = FakeAgent()
    L = OnlineLearner(agent, step_ns=S)
    for k in range(10):
        step(L, k, float(k))
    old = list(agent.observed)
    assert len(old) == 9 and L.pending_stamp == 9 * S
    assert step(L, 0, 0.0) == []  # one step back: could be a stale copy, not followed yet
    d = step(L, 1, 5.0)  # a second consecutive one: the stream jumped
    assert [x.stamp_ns for x in d] == [S] and d[0].action is not None and not d[0].stored
    assert L.counters["stream_jumps"] == 1 and L.counters["abandoned_episodes"] == 1
    assert agent.observed == old  # the open transition was dropped, not joined across streams
    for k in range(2, 6):
        assert step(L, k, float(k))[0].stored
    assert [o[0] for o in agent.observed[len(old):]] == [1.0, 2.0, 3.0, 4.0]
    assert L.counters["stale_state"] == 1 and L.counters["stale_reward"] == 1  # step 0 of the new stream


@pytest.mark.parametrize("step_ns", [S, None], ids=["step known", "step unknown"])
def test_one_absurd_future_stamp_cannot_mute_the_agent(step_ns):
    agent = FakeAgent()
    L = OnlineLearner(agent, step_ns=step_ns)
    for k in range(5):
        step(L, k, 1.0)
    far = 10**18
    L.on_reward(far, 7.0, False, False)
    forged = L.on_state(far, obs(99))
    answered = []
    for k in range(5, 25):
        answered += [d.stamp_ns for d in step(L, k, 1.0) if d.action is not None]
    if step_ns is not None:  # outside the window: parked, never answered, the stream goes on uninterrupted
        assert forged == [] and answered == [k * S for k in range(5, 25)]
        assert L.counters["gaps"] == 0 and L.counters["stream_jumps"] == 0
        assert all(o[0] != 99.0 and o[3] != 99.0 for o in agent.observed)
    else:  # it moves the stream once; the second step after it brings the agent back
        assert [d.stamp_ns for d in forged] == [far]
        assert answered == [k * S for k in range(6, 25)] and L.counters["stream_jumps"] == 1
    assert L.counters["stale_state"] + L.counters["stale_reward"] >= 1


def test_a_single_replayed_pair_never_moves_the_stream():
    agent = FakeAgent()
    L = OnlineLearner(agent, step_ns=S)
    for k in range(6):
        step(L, k, 1.0)
    assert step(L, 2, 9.0) == []  # a copy of an old step (both halves)
    assert step(L, 6, 1.0)[0].stored  # the stream goes on, no transition lost
    assert L.counters["stream_jumps"] == 0 and L.counters["stale_state"] == 1


def test_parked_and_buffered_halves_are_bounded_first_in_first_out():
    L = OnlineLearner(FakeAgent(), max_buffered=4, step_ns=S)
    step(L, 0, 0.0)
    L.on_state(3 * S, obs(3))  # a legit half waiting for its reward
    for k in range(10):
        L.on_state(10**15 + k * S, obs(k))  # a flood of future stamps: parked, never pins the buffer
    assert L.buffered == 1 and L.counters["evicted"] == 6 and L.counters["stale_state"] == 10
    assert L.on_reward(3 * S, 1.0, False, False)[0].stamp_ns == 3 * S


def test_the_contract_parsers_reject_non_finite_and_out_of_float32_values():
    """Offline tools (export) decode with the same parsers as the nodes: a poisoned bag cannot produce NaNs."""
    from types import SimpleNamespace

    from der_ros import contract as ct

    def reward(x):
        return SimpleNamespace(vector=SimpleNamespace(x=x, y=0.0, z=0.0),
                               header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0), frame_id=""))

    for x in (float("nan"), float("inf"), 1e300):
        with pytest.raises(ValueError, match="expected a finite number within float32 range"):
            ct.parse_reward(reward(x))
    assert ct.parse_reward(reward(-3e38)).reward == -3e38
    fields = [SimpleNamespace(name=n, datatype=ct.POINTFIELD_FLOAT64, offset=8 * i, count=1) for i, n in enumerate("ab")]
    for bad in (np.nan, -np.inf, 1e39):
        data = np.array([[0.0, 1.0], [2.0, bad]], dtype="<f8").tobytes()
        cloud = SimpleNamespace(fields=fields, width=2, height=1, point_step=16, data=data, is_bigendian=False)
        with pytest.raises(ValueError, match="state point 1 field 'b' = .*, expected a finite number"):
            ct.cloud_to_points(cloud)
