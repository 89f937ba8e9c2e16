"""DQN learner: targets, loss weighting, priorities feedback, epsilon, target updates, networks, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from der_ros.agent.config import DQNConfig
from der_ros.agent.dqn import DQNAgent
from der_ros.agent.networks import AtariCNN, MLPQNetwork, flatten_parameters
from der_ros.agent.optim import FlatAdam
from der_ros.agent.schedules import LinearSchedule
from der_ros.replay.base import Batch
from der_ros.replay.config import ReplayConfig

GAMMA = 0.9


def small_agent(**cfg: object) -> DQNAgent:
    dqn = DQNConfig(
        **{
            "gamma": GAMMA,
            "batch_size": 4,
            "hidden_sizes": [16],
            "learning_starts": 0,
            "max_grad_norm": 0.0,
            **cfg,
        }
    )
    return DQNAgent((3,), np.float32, 2, dqn, ReplayConfig(kind="uniform", capacity=100), seed=0)


def set_constant_q(net: MLPQNetwork, values: list[float]) -> None:
    """Make a network output the same Q-values for every input: zero weights, last bias = values."""
    with torch.no_grad():
        for layer in net._linears:
            layer.weight.zero_()
            layer.bias.zero_()
        net._linears[-1].bias.copy_(torch.tensor(values))


class SpyReplay:
    """Returns one fixed batch and records the update_priorities calls."""

    def __init__(self, batch: Batch) -> None:
        self.batch = batch
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, *transition: object) -> None:
        pass

    def sample(self, batch_size: int) -> Batch:
        return self.batch

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        self.calls.append((indices.copy(), td_errors.copy()))

    def __len__(self) -> int:
        return 1000

    def stats(self) -> dict[str, float]:
        return {"replay/size": 1000.0}


def hand_batch(weights: list[float] | None = None) -> Batch:
    # rows: terminal, truncated (not terminal), ordinary, terminal+truncated
    return Batch(
        obs=np.arange(12, dtype=np.float32).reshape(4, 3) / 10,
        actions=np.array([0, 1, 0, 1], dtype=np.int64),
        rewards=np.array([1.0, 2.0, 3.0, -1.0], dtype=np.float32),
        next_obs=np.ones((4, 3), dtype=np.float32),
        terminated=np.array([True, False, False, True]),
        truncated=np.array([False, True, False, True]),
        indices=np.array([10, 11, 12, 13], dtype=np.int64),
        weights=np.asarray(weights or [1.0, 1.0, 1.0, 1.0], dtype=np.float32),
        source=np.zeros(4, dtype=np.uint8),
    )


def test_targets_cut_bootstrap_on_terminated_only() -> None:
    agent = small_agent()
    set_constant_q(agent.target_net, [2.0, 5.0])
    b = hand_batch()
    y = agent.td_targets(torch.from_numpy(b.rewards), torch.from_numpy(b.next_obs), torch.from_numpy(b.terminated))
    # terminal rows: y = r; truncated-but-not-terminal row bootstraps like an ordinary row
    expected = np.array([1.0, 2.0 + GAMMA * 5.0, 3.0 + GAMMA * 5.0, -1.0], dtype=np.float32)
    np.testing.assert_allclose(y.numpy(), expected, rtol=1e-6)


def test_double_dqn_target_uses_online_argmax() -> None:
    agent = small_agent(double_dqn=True)
    set_constant_q(agent.target_net, [2.0, 5.0])
    set_constant_q(agent.q_net, [3.0, 0.0])  # online net prefers action 0 -> target evaluates Q_t(s', 0) = 2
    b = hand_batch()
    y = agent.td_targets(torch.from_numpy(b.rewards), torch.from_numpy(b.next_obs), torch.from_numpy(b.terminated))
    np.testing.assert_allclose(y.numpy(), [1.0, 2.0 + GAMMA * 2.0, 3.0 + GAMMA * 2.0, -1.0], rtol=1e-6)


@pytest.mark.parametrize("loss", ["mse", "huber"])
def test_gradient_step_weights_loss_and_feeds_td_errors_back(loss: str) -> None:
    agent = small_agent(loss=loss)
    weights = [0.5, 2.0, 1.0, 0.0]
    spy = SpyReplay(hand_batch(weights))
    agent.replay = spy  # type: ignore[assignment]
    b = spy.batch
    with torch.no_grad():
        q = agent.q_net(torch.from_numpy(b.obs)).gather(1, torch.from_numpy(b.actions)[:, None])[:, 0].numpy()
        y = agent.td_targets(torch.from_numpy(b.rewards), torch.from_numpy(b.next_obs), torch.from_numpy(b.terminated))
    delta = y.numpy() - q
    if loss == "mse":
        per = delta**2
    else:
        a = np.abs(delta)
        per = np.where(a < 1.0, 0.5 * delta**2, a - 0.5)
    expected_loss = float(np.mean(np.asarray(weights) * per))

    agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
    metrics = agent.learn()
    assert metrics["losses/td_loss"] == pytest.approx(expected_loss, rel=1e-5)
    assert metrics["losses/abs_td_error"] == pytest.approx(float(np.abs(delta).mean()), rel=1e-5)
    assert metrics["losses/q_values"] == pytest.approx(float(q.mean()), rel=1e-5, abs=1e-7)
    assert len(spy.calls) == 1
    idx, td = spy.calls[0]
    np.testing.assert_array_equal(idx, b.indices)
    np.testing.assert_allclose(td, delta, rtol=1e-5, atol=1e-6)


def test_reward_scale_scales_rewards_before_the_target_and_td_errors() -> None:
    """reward_scale = 0.01 (the authors' r/100) on rewards r gives the TD errors that raw rewards r/100 give:
    the replay keeps raw rewards, the learner scales them before eq. 1, so DER's weights e^|delta| see |delta| ~ 1."""
    deltas = []
    for scale, factor in ((0.01, 1.0), (1.0, 0.01)):
        agent = small_agent(reward_scale=scale)
        b = hand_batch()
        spy = SpyReplay(b._replace(rewards=(b.rewards * 100.0 * factor).astype(np.float32)))
        agent.replay = spy  # type: ignore[assignment]
        agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
        assert agent.learn()
        deltas.append(spy.calls[0][1])
    np.testing.assert_allclose(deltas[0], deltas[1], rtol=1e-6)
    assert np.abs(deltas[0]).max() < 10.0  # r up to 300 raw, scaled to 3


def test_zero_weights_leave_network_unchanged() -> None:
    agent = small_agent()
    agent.replay = SpyReplay(hand_batch([0.0, 0.0, 0.0, 0.0]))  # type: ignore[assignment]
    before = [p.detach().clone() for p in agent.q_net.parameters()]
    agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
    assert agent.learn()
    assert all(torch.equal(a, b) for a, b in zip(before, agent.q_net.parameters()))
    agent.replay = SpyReplay(hand_batch([1.0, 1.0, 1.0, 1.0]))  # type: ignore[assignment]
    agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
    assert agent.learn()
    assert not all(torch.equal(a, b) for a, b in zip(before, agent.q_net.parameters()))


def test_gradient_step_now_and_learning_rate_change() -> None:
    agent = small_agent()
    agent.replay = SpyReplay(hand_batch())  # type: ignore[assignment]
    for group in agent.optimizer.param_groups:  # how the ROS node changes agent.lr at run time
        group["lr"] = 0.0
    before = [p.detach().clone() for p in agent.q_net.parameters()]
    loss, _q, abs_td = agent.gradient_step()
    assert loss > 0 and abs_td > 0 and agent.grad_steps == 1
    assert all(torch.equal(a, b) for a, b in zip(before, agent.q_net.parameters()))
    agent.optimizer.param_groups[0]["lr"] = 1e-2
    agent.gradient_step()
    assert not all(torch.equal(a, b) for a, b in zip(before, agent.q_net.parameters()))


def test_learn_schedule_learning_starts_train_freq_gradient_steps() -> None:
    agent = small_agent(learning_starts=5, train_freq=2, gradient_steps=3, target_update_interval=1000)
    spy = SpyReplay(hand_batch())
    agent.replay = spy  # type: ignore[assignment]
    due = []
    for _ in range(10):
        agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
        due.append(bool(agent.learn()))
        assert agent.learn() == {}  # a second call at the same step does nothing
    assert due == [False, False, False, False, False, True, False, True, False, True]
    assert agent.grad_steps == 9 and len(spy.calls) == 9


def test_linear_epsilon_schedule() -> None:
    s = LinearSchedule(1.0, 0.1, 100)
    assert s(0) == 1.0
    assert s(50) == pytest.approx(0.55)
    assert s(100) == pytest.approx(0.1)
    assert s(10_000) == pytest.approx(0.1)
    assert LinearSchedule(1.0, 0.1, 0)(0) == pytest.approx(0.1)
    agent = small_agent(epsilon_start=1.0, epsilon_end=0.0, epsilon_decay_steps=10)
    obs = np.zeros(3, np.float32)
    greedy = int(np.argmax(agent.q_values(obs)))
    # epsilon = 1: about half of the actions differ from the greedy one; epsilon = 0: none
    random_actions = [agent.act(obs) for _ in range(400)]
    assert 0.4 < np.mean(np.asarray(random_actions) != greedy) < 0.6
    for _ in range(10):
        agent.observe(obs, 0, 0.0, obs, False, False)
    assert agent.epsilon == 0.0
    assert all(agent.act(obs) == greedy for _ in range(50))


def test_hard_target_update_every_n_gradient_steps() -> None:
    agent = small_agent(target_update_interval=3, tau=1.0)
    agent.replay = SpyReplay(hand_batch())  # type: ignore[assignment]
    t0 = [p.detach().clone() for p in agent.target_net.parameters()]
    for step in range(1, 4):
        agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
        agent.learn()
        same_as_online = all(torch.equal(t, o) for t, o in zip(agent.target_net.parameters(), agent.q_net.parameters()))
        unchanged = all(torch.equal(t, p) for t, p in zip(agent.target_net.parameters(), t0))
        if step < 3:
            assert unchanged and not same_as_online
        else:
            assert same_as_online and not unchanged


@pytest.mark.slow
def test_polyak_target_update() -> None:
    tau = 0.1
    agent = small_agent(target_update_interval=1, tau=tau)
    agent.replay = SpyReplay(hand_batch())  # type: ignore[assignment]
    before = [p.detach().clone() for p in agent.target_net.parameters()]
    agent.observe(np.zeros(3, np.float32), 0, 0.0, np.zeros(3, np.float32), False, False)
    agent.learn()
    for t, b, o in zip(agent.target_net.parameters(), before, agent.q_net.parameters()):
        torch.testing.assert_close(t, (1 - tau) * b + tau * o, rtol=1e-6, atol=1e-7)
        assert not torch.equal(t, b)


def test_flat_parameters_alias_module_and_receive_gradients() -> None:
    torch.manual_seed(0)
    net = MLPQNetwork(4, 2, [8])
    reference = MLPQNetwork(4, 2, [8])
    reference.load_state_dict(net.state_dict())
    flat, grad = flatten_parameters(net)
    x = torch.randn(5, 4)
    net(x).square().sum().backward()
    reference.net(x).square().sum().backward()  # the plain nn.Sequential path
    torch.testing.assert_close(grad, torch.cat([p.grad.reshape(-1) for p in reference.parameters()]))
    opt = FlatAdam(flat, grad, lr=1e-2)
    ref_opt = torch.optim.Adam(reference.parameters(), lr=1e-2)
    opt.step()
    ref_opt.step()
    for a, b in zip(net.parameters(), reference.parameters()):
        torch.testing.assert_close(a, b)


def test_atari_cnn_on_real_preprocessed_frames() -> None:
    from der_ros.train.envs import make_env, obs_spec

    env = make_env("ALE/Breakout-v5", seed=0)
    try:
        obs, _ = env.reset(seed=0)
        for _ in range(8):
            obs, *_ = env.step(env.action_space.sample())
    finally:
        env.close()
    assert obs.shape == (4, 84, 84) and obs.dtype == np.uint8 and obs.max() > 0
    shape, dtype = obs_spec(env)
    agent = DQNAgent(
        shape,
        dtype,
        int(env.action_space.n),
        DQNConfig(batch_size=2, learning_starts=0),
        ReplayConfig(kind="uniform", capacity=10),
        seed=0,
    )
    assert isinstance(agent.q_net, AtariCNN)
    batch = torch.from_numpy(np.stack([obs, obs]))
    q = agent.q_net(batch)
    assert q.shape == (2, 4) and q.dtype == torch.float32
    # frames are scaled by 1/255 inside the net: feeding the float frames / 255 through the layers
    # without the scaling gives the same values
    manual = agent.q_net.head(agent.q_net.features(batch.float() / 255.0))
    torch.testing.assert_close(q, manual)
    agent.observe(obs, 1, 1.0, obs, False, False)
    agent.observe(obs, 2, 0.0, obs, True, False)
    assert agent.replay.sample(2).obs.dtype == np.uint8  # stored as uint8
    assert "losses/td_loss" in agent.learn()


def synthetic_transition(k: int, action: int) -> tuple[np.ndarray, float, np.ndarray, bool, bool]:
    """A deterministic 'environment': transition k depends only on k and the action."""
    rng = np.random.default_rng(1000 + k)
    obs = rng.normal(size=3).astype(np.float32)
    next_obs = (obs + 0.1 * action).astype(np.float32)
    return obs, float(rng.normal()) + action, next_obs, k % 17 == 16, k % 23 == 22


def drive(agent: DQNAgent, start: int, stop: int) -> list[float]:
    losses = []
    for k in range(start, stop):
        obs, _, _, _, _ = synthetic_transition(k, 0)
        a = agent.act(obs)
        obs, r, nxt, term, trunc = synthetic_transition(k, a)
        agent.observe(obs, a, r, nxt, term, trunc)
        m = agent.learn()
        if m:
            losses.append(m["losses/td_loss"])
    return losses


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["uniform", "per", "der"])
def test_checkpoint_resume_is_bit_exact(kind: str, tmp_path) -> None:
    dqn = DQNConfig(
        batch_size=16,
        hidden_sizes=[32],
        learning_starts=20,
        epsilon_decay_steps=150,
        target_update_interval=25,
        max_grad_norm=1.0,
    )
    rep = ReplayConfig(kind=kind, capacity=300, lam=0.5, h2_capacity=64)
    n, m = 120, 80

    straight = DQNAgent((3,), np.float32, 2, dqn, rep, seed=7)
    losses_straight = drive(straight, 0, n + m)

    first = DQNAgent((3,), np.float32, 2, dqn, rep, seed=7)
    losses_first = drive(first, 0, n)
    path = first.save(tmp_path / "ckpt.pt")
    del first
    resumed = DQNAgent.load(path)
    losses_second = drive(resumed, n, n + m)

    assert losses_first + losses_second == losses_straight
    assert resumed.steps == straight.steps and resumed.grad_steps == straight.grad_steps
    for a, b in zip(resumed.q_net.parameters(), straight.q_net.parameters()):
        assert torch.equal(a, b)
    for a, b in zip(resumed.target_net.parameters(), straight.target_net.parameters()):
        assert torch.equal(a, b)
    assert torch.equal(resumed.optimizer.exp_avg_sq, straight.optimizer.exp_avg_sq)
    sa, sb = resumed.replay.state_dict(), straight.replay.state_dict()
    assert sa.keys() == sb.keys()
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=key)
    assert resumed.rng.bit_generator.state == straight.rng.bit_generator.state
    # a different seed gives a different run (the comparison above is not vacuous)
    other = DQNAgent((3,), np.float32, 2, dqn, rep, seed=8)
    drive(other, 0, n + m)
    assert not all(torch.equal(a, b) for a, b in zip(other.q_net.parameters(), straight.q_net.parameters()))


def test_save_is_atomic_and_load_rejects_other_shapes(tmp_path) -> None:
    agent = small_agent()
    path = agent.save(tmp_path / "a.pt")
    assert path.is_file() and [p.name for p in tmp_path.iterdir()] == ["a.pt"]  # no temp file left
    state = torch.load(path, weights_only=False)["agent"]
    other = DQNAgent((5,), np.float32, 2, agent.cfg, agent.replay_cfg)
    with pytest.raises(ValueError, match="obs_shape"):
        other.load_state_dict(state)


class AutogradReferenceAgent(DQNAgent):
    """The gradient step written the straightforward way (autograd, as the learner did before the
    hand-written backward of der_ros/agent/mlp_backward.py): the fast step must match it bit for bit."""

    def _gradient_step(self) -> tuple[float, float, float]:
        c = self.cfg
        batch = self.replay.sample(c.batch_size)
        obs, next_obs = torch.from_numpy(batch.obs), torch.from_numpy(batch.next_obs)
        actions = torch.from_numpy(batch.actions.astype(np.int64))
        rewards = torch.from_numpy(batch.rewards.astype(np.float32)) * c.reward_scale
        terminated = torch.from_numpy(batch.terminated)
        weights = torch.from_numpy(batch.weights.astype(np.float32))
        with torch.no_grad():
            next_q = self.target_net(next_obs)
            if c.double_dqn:
                next_v = next_q.gather(1, self.q_net(next_obs).argmax(1, keepdim=True)).squeeze(1)
            else:
                next_v = next_q.max(1).values
            y = rewards + c.gamma * (1.0 - terminated.float()) * next_v
        q = self.q_net(obs).gather(1, actions.unsqueeze(1)).squeeze(1)
        td = y - q
        per_sample = td.square() if c.loss == "mse" else torch.nn.functional.smooth_l1_loss(q, y, reduction="none")
        loss = (weights * per_sample).mean()
        for p in self.q_net.parameters():
            p.grad.zero_()
        loss.backward()
        if c.max_grad_norm > 0.0:
            norm = torch.linalg.vector_norm(self._flat_grad)
            self._flat_grad.mul_(torch.clamp(c.max_grad_norm / (norm + 1e-6), max=1.0))
        opt = self.optimizer
        opt.step_count += 1
        with torch.no_grad():  # Adam, as FlatAdam wrote it before (fresh tensors every step)
            g, t = opt.grads, opt.step_count
            opt.exp_avg.lerp_(g, 1.0 - opt.beta1)
            opt.exp_avg_sq.mul_(opt.beta2).addcmul_(g, g, value=1.0 - opt.beta2)
            denom = (opt.exp_avg_sq.sqrt() / (1.0 - opt.beta2**t) ** 0.5).add_(opt.eps)
            opt.params.addcdiv_(opt.exp_avg, denom, value=-opt.lr / (1.0 - opt.beta1**t))
        self.grad_steps += 1
        if self.grad_steps % c.target_update_interval == 0:
            self.update_target()
        td_np = td.detach().numpy()
        self.replay.update_priorities(batch.indices, td_np)
        n = len(td_np)
        return float(loss.item()), float(np.add.reduce(q.detach().numpy())) / n, float(np.add.reduce(np.abs(td_np))) / n


def _bits(t: torch.Tensor) -> bytes:
    return t.detach().contiguous().numpy().tobytes()


@pytest.mark.parametrize(
    "kind, overrides",
    [
        ("uniform", {}),
        ("per", {"max_grad_norm": 0.5, "batch_size": 50}),  # clipping in most steps; IS weights with an inexact 1/B
        ("der", {"reward_scale": 0.01, "batch_size": 50}),  # 1/B inexact in float32
        ("der", {"double_dqn": True, "tau": 0.3, "hidden_sizes": [16, 8]}),  # two hidden layers
        ("uniform", {"max_grad_norm": 0.0, "target_update_interval": 7}),
        ("per", {"loss": "huber"}),  # autograd path in both
    ],
)
def test_learner_step_is_bit_identical_to_the_autograd_reference(kind: str, overrides: dict) -> None:
    dqn = DQNConfig(**{"batch_size": 32, "hidden_sizes": [32], "learning_starts": 40, "gamma": 0.98,
                       "target_update_interval": 20, "max_grad_norm": 10.0, "epsilon_decay_steps": 100, **overrides})  # fmt: skip
    rep = ReplayConfig(kind=kind, capacity=400, lam=0.9, h2_capacity=128, promote_mode="copy")
    fast = DQNAgent((5,), np.float32, 3, dqn, rep, seed=3)
    ref = AutogradReferenceAgent((5,), np.float32, 3, dqn, rep, seed=3)
    assert (fast._mlp is not None) == (dqn.loss == "mse")  # the hand-written backward is what is tested
    rng = np.random.default_rng(0)
    for _ in range(260):
        obs, nxt = rng.normal(size=(2, 5)).astype(np.float32)
        a = fast.act(obs)
        assert ref.act(obs) == a
        r, term, trunc = float(rng.normal() * 50.0), bool(rng.random() < 0.1), bool(rng.random() < 0.05)
        for agent in (fast, ref):
            agent.observe(obs, a, r, nxt, term, trunc)
        assert fast.learn() == ref.learn()  # metrics: the same floats
    assert fast.grad_steps == ref.grad_steps > 200
    for mine, theirs in ((fast.q_net, ref.q_net), (fast.target_net, ref.target_net)):
        for p, q in zip(mine.parameters(), theirs.parameters()):
            assert _bits(p) == _bits(q)
    assert _bits(fast.optimizer.exp_avg) == _bits(ref.optimizer.exp_avg)
    assert _bits(fast.optimizer.exp_avg_sq) == _bits(ref.optimizer.exp_avg_sq)
    sa, sb = fast.replay.state_dict(), ref.replay.state_dict()
    for key in sa:  # priorities and DER weights come from the TD errors
        assert np.asarray(sa[key]).tobytes() == np.asarray(sb[key]).tobytes(), key


def test_fast_paths_follow_weights_loaded_from_a_checkpoint() -> None:
    """act() and the TD targets read the networks through detached views of their weights: after
    load_state_dict they must see the loaded weights, not the ones the agent was built with."""
    src, dst = small_agent(), small_agent()
    rng = np.random.default_rng(1)
    with torch.no_grad():  # make src's networks differ from dst's (same seed, same initial weights)
        for net in (src.q_net, src.target_net):
            for p in net.parameters():
                p.copy_(torch.from_numpy(rng.normal(size=tuple(p.shape)).astype(np.float32)))
    dst.load_state_dict(src.state_dict())
    obs = rng.normal(size=(64, 3)).astype(np.float32)
    with torch.no_grad():
        want_actions = src.q_net(torch.from_numpy(obs)).argmax(1).numpy()
        want_next_v = src.target_net(torch.from_numpy(obs)).amax(1).numpy()
    assert [dst.act(o, explore=False) for o in obs] == want_actions.tolist()
    assert len(set(want_actions.tolist())) == 2  # both actions occur: the check could fail
    y = dst.td_targets(torch.zeros(64), torch.from_numpy(obs), torch.zeros(64, dtype=torch.bool))
    np.testing.assert_array_equal(y.numpy(), np.float32(GAMMA) * want_next_v)
