"""The shield's mask reaches the learner: its action choice and its target's max (der_ros/agent/dqn.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from der_ros.agent.config import DQNConfig
from der_ros.agent.dqn import DQNAgent
from der_ros.replay.config import ReplayConfig


def agent(double: bool = False, seed: int = 0) -> DQNAgent:
    dqn = DQNConfig(batch_size=8, learning_starts=0, hidden_sizes=(16,), double_dqn=double, epsilon_start=0.5,
                    epsilon_end=0.5, target_update_interval=1000)  # fmt: skip
    return DQNAgent((4,), np.float32, 3, dqn, ReplayConfig(kind="uniform", capacity=64), seed=seed)


def fill(a: DQNAgent, n: int = 32, seed: int = 1) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(n):
        o, o2 = rng.normal(size=4).astype(np.float32), rng.normal(size=4).astype(np.float32)
        a.observe(o, int(rng.integers(3)), float(rng.normal()), o2, bool(rng.random() < 0.1), False)


def test_act_chooses_only_allowed_actions() -> None:
    a = agent()
    obs = np.ones(4, dtype=np.float32)
    greedy = a.act(obs, explore=False)
    mask = np.ones(3, dtype=bool)
    mask[greedy] = False
    for _ in range(200):  # epsilon 0.5: random and greedy choices both happen
        assert mask[a.act(obs, mask=mask)]
    only_keep = np.array([True, False, False])
    assert all(a.act(obs, mask=only_keep) == 0 for _ in range(50))
    with pytest.raises(ValueError, match="allows no action"):
        a.act(obs, mask=np.zeros(3, dtype=bool))


@pytest.mark.parametrize("double", [False, True])
def test_target_max_runs_over_allowed_next_actions(double: bool) -> None:
    a = agent(double)
    next_obs = torch.from_numpy(np.random.default_rng(2).normal(size=(8, 4)).astype(np.float32))
    rewards, discount = torch.zeros(8), torch.full((8,), 0.9)
    q = a.target_net(next_obs).detach()
    best = q.argmax(1)
    forbid = torch.zeros(8, 3, dtype=torch.bool)
    forbid[torch.arange(8), best] = True  # forbid the unmasked max everywhere
    forbid[:, 0] = False  # keep stays allowed
    y_plain = a._targets(rewards, next_obs, discount)
    y_masked = a._targets(rewards, next_obs, discount, forbid)
    expected = 0.9 * q.masked_fill(forbid, -np.inf).amax(1)
    if not double:
        torch.testing.assert_close(y_masked, expected)
    changed = best != 0
    assert changed.any()
    assert (y_masked[changed] < y_plain[changed]).all() if not double else torch.isfinite(y_masked).all()


def test_gradient_step_asks_the_mask_of_the_sampled_next_states() -> None:
    a = agent()
    fill(a)
    seen: list[np.ndarray] = []

    def only_keep(next_obs: np.ndarray) -> np.ndarray:
        seen.append(np.array(next_obs))
        out = np.zeros((len(next_obs), 3), dtype=bool)
        out[:, 0] = True
        return out

    a.target_mask = only_keep
    with torch.no_grad():
        a.learn()
    assert len(seen) == 1 and seen[0].shape == (8, 4)
    # every sampled next state is one the replay holds
    stored = {tuple(r) for r in a.replay.storage.next_obs[: len(a.replay)].tolist()}
    assert all(tuple(r) in stored for r in seen[0].tolist())


def test_allow_all_mask_is_bit_identical_to_no_mask() -> None:
    plain, masked = agent(seed=3), agent(seed=3)
    fill(plain)
    fill(masked)
    masked.target_mask = lambda nxt: np.ones((len(nxt), 3), dtype=bool)
    for _ in range(5):
        plain.steps += 1
        masked.steps += 1
        plain.learn()
        masked.learn()
    for p, m in zip(plain.q_net.parameters(), masked.q_net.parameters()):
        assert torch.equal(p, m)


def test_masked_training_differs_from_unmasked() -> None:
    plain, masked = agent(seed=4), agent(seed=4)
    fill(plain)
    fill(masked)
    masked.target_mask = lambda nxt: np.tile(np.array([True, False, False]), (len(nxt), 1))
    for _ in range(3):
        plain.steps += 1
        masked.steps += 1
        plain.learn()
        masked.learn()
    assert any(not torch.equal(p, m) for p, m in zip(plain.q_net.parameters(), masked.q_net.parameters()))
