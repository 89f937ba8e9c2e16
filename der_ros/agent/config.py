"""DQNConfig: every hyperparameter of the DQN learner (paper section 2.1, eq. 1; section 4).

The paper gives the optimiser (Adam), the learning rate, gamma, the batch size and the network
sizes. It does not give the exploration schedule, the target-network update, when learning starts
or how often the network is trained; the defaults below are our choices, the same for every
replay method (uniform / PER / DER), and are repeated in the YAML files of ``config/``.
"""

from __future__ import annotations

from dataclasses import dataclass

from der_ros.configuration import ConfigError, param

__all__ = ["DQNConfig"]


@dataclass
class DQNConfig:
    """Hyperparameters of :class:`der_ros.agent.dqn.DQNAgent`."""

    lr: float = param(5e-4, "Adam learning rate (paper sections 4.1 and 5: 0.0005); above 1 it is a typo, never a setting",
                      low=0.0, low_inclusive=False, high=1.0)
    gamma: float = param(0.98, "discount factor gamma of eq. 1 (paper: 0.98 CartPole, 0.99 Atari)", low=0.0, high=1.0)
    batch_size: int = param(128, "transitions per gradient step (paper: 128)", low=1)
    reward_scale: float = param(
        1.0,
        "the learner multiplies every reward by this before the TD target (the replay keeps raw rewards). "
        "It sets the scale of the TD errors, and so of DER's weights p = e^|delta| (eq. 3) and PER's "
        "priorities: the authors' code stores r/100 (0.01), so that |delta| ~ 1 on SUMO's +-100 rewards "
        "instead of a collision weighing e^100. The same for every replay method",
        low=0.0,
        low_inclusive=False,
    )
    network: str = param(
        "auto",
        "Q-network: 'mlp' (vector observations), 'cnn' (the paper's Atari CNN on 4x84x84 uint8 frames) "
        "or 'auto' (cnn for 3-D uint8 observations, mlp otherwise)",
        choices=("auto", "mlp", "cnn"),
    )
    hidden_sizes: list[int] = param(
        default_factory=lambda: [256],
        help="hidden layer widths of the MLP (paper section 4.1: one layer of 256 units)",
    )
    loss: str = param(
        "mse",
        "TD loss: 'mse' = squared TD error as in eq. 1, 'huber' = smooth L1 (less sensitive to outliers)",
        choices=("mse", "huber"),
    )
    double_dqn: bool = param(
        False, "double-DQN target: the online net picks argmax_a', the target net evaluates it (off in the paper)"
    )
    max_grad_norm: float = param(
        10.0, "clip the global gradient norm to this value before each Adam step; 0 disables clipping", low=0.0
    )
    target_update_interval: int = param(
        200,
        "update the target network every this many gradient steps (hard copy when tau = 1; our choice, "
        "not given by the paper)",
        low=1,
    )
    tau: float = param(
        1.0,
        "target update rate: 1.0 = hard copy, < 1 = Polyak averaging target <- tau*online + (1-tau)*target",
        low=0.0,
        high=1.0,
        low_inclusive=False,
    )
    learning_starts: int = param(500, "environment steps collected before the first gradient step (our choice)", low=0)
    train_freq: int = param(1, "do gradient steps every this many environment steps", low=1)
    gradient_steps: int = param(1, "gradient steps each time training is due", low=1)
    epsilon_start: float = param(1.0, "epsilon of the epsilon-greedy policy at step 0", low=0.0, high=1.0)
    epsilon_end: float = param(0.02, "epsilon after the linear decay", low=0.0, high=1.0)
    epsilon_decay_steps: int = param(
        2000,
        "environment steps over which epsilon falls linearly from epsilon_start to epsilon_end, then stays "
        "(our choice; the paper uses epsilon-greedy without a schedule)",
        low=0,
    )
    eval_epsilon: float = param(0.0, "epsilon of act(explore=False) (greedy by default)", low=0.0, high=1.0)

    def check(self) -> None:
        if self.epsilon_end > self.epsilon_start:
            raise ConfigError(f"epsilon_end = {self.epsilon_end!r}, expected <= epsilon_start ({self.epsilon_start!r})")
        if not self.hidden_sizes or any(h < 1 for h in self.hidden_sizes):
            raise ConfigError(f"hidden_sizes = {self.hidden_sizes!r}, expected a non-empty list of positive integers")
