"""DQNAgent: the DQN learner of paper section 2.1 with any replay kind (uniform / PER / DER).

Step-wise API (docs/architecture.md, "Learner step-wise API"), so that both ``der train`` and the
ROS agent node, which receives one message at a time, can drive it::

    a = agent.act(obs)                                   # epsilon-greedy by agent.steps
    agent.observe(obs, a, r, next_obs, terminated, truncated)
    metrics = agent.learn()                              # {} unless a gradient step was due

Learning rule (eq. 1 and eq. 2 of the paper), with r scaled by ``reward_scale``::

    y = r + gamma * (1 - terminated) * max_a' Q_target(s', a')
    delta = y - Q(s, a)
    L = mean_i( w_i * delta_i^2 )          (or the Huber loss of delta)

Only ``terminated`` cuts the bootstrap: a time limit (``truncated``) is not a property of the
state, so the value of s' is still bootstrapped there. ``w_i`` are the replay's importance weights
(1 for uniform and DER, PER's IS weights), and every batch's TD errors go back to the replay via
``update_priorities`` (for DER that call promotes H1 transitions to H2 and applies eq. 3).
"""

from __future__ import annotations

import copy
import logging
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from der_ros.agent.config import DQNConfig
from der_ros.agent.divergence import LearnerDiverged, diverged_path
from der_ros.agent.mlp_backward import MLPBackward, detached_layers, mlp_forward
from der_ros.agent.networks import MLPQNetwork, flatten_parameters, make_q_network
from der_ros.agent.optim import FlatAdam
from der_ros.agent.schedules import LinearSchedule
from der_ros.configuration import from_dict, to_dict
from der_ros.replay.config import ReplayConfig
from der_ros.replay.factory import make_replay

__all__ = ["DQNAgent", "LearnerDiverged", "resolve_device", "read_checkpoint", "diverged_path", "CHECKPOINT_VERSION"]

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1


def resolve_device(device: str | torch.device) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cpu' / 'cuda' / 'cuda:1' as given."""
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device = {device!r}, but CUDA is not available on this machine (use 'cpu' or 'auto')")
    return torch.device(device)


class DQNAgent:
    """DQN with a target network, epsilon-greedy exploration and a pluggable replay buffer.

    Randomness: one numpy Generator for exploration, the replay's own generator for sampling, and
    torch's generator only for the initial weights (drawn inside ``fork_rng`` so that building an
    agent does not disturb the caller's torch RNG). All of it is in :meth:`state_dict`, so a run
    resumed from a checkpoint continues bit-for-bit like the uninterrupted run (on CPU).
    """

    def __init__(
        self,
        obs_shape: tuple[int, ...],
        obs_dtype: np.dtype | type | str,
        n_actions: int,
        dqn_cfg: DQNConfig,
        replay_cfg: ReplayConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.obs_shape = tuple(int(s) for s in obs_shape)
        self.obs_dtype = np.dtype(obs_dtype)
        self.n_actions = int(n_actions)
        self.cfg = dqn_cfg
        self.replay_cfg = replay_cfg
        self.seed = int(seed)
        self.device = resolve_device(device)

        seeds = np.random.SeedSequence(self.seed).spawn(3)
        self.rng = np.random.default_rng(seeds[0])
        replay_seed = int(seeds[1].generate_state(1, dtype=np.uint32)[0])
        torch_seed = int(seeds[2].generate_state(1, dtype=np.uint32)[0])

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(torch_seed)
            self.q_net = make_q_network(
                self.obs_shape, self.obs_dtype, self.n_actions, dqn_cfg.network, dqn_cfg.hidden_sizes
            ).to(self.device)
        self.target_net = copy.deepcopy(self.q_net)
        self.target_net.requires_grad_(False)
        # One contiguous buffer per network (parameters are views of it): Adam, clipping and the
        # target update are then single-tensor operations -- the hot path of a small-net DQN.
        self._flat, self._flat_grad = flatten_parameters(self.q_net)
        self._target_flat, _ = flatten_parameters(self.target_net, with_grad=False)
        self.optimizer = FlatAdam(self._flat, self._flat_grad, lr=dqn_cfg.lr)
        self.replay = make_replay(replay_cfg, self.obs_shape, self.obs_dtype, dqn_cfg.batch_size, replay_seed)
        # the learner step's constants and buffers (see _gradient_step)
        self._on_cpu = self.device.type == "cpu"
        self._gamma32 = np.float32(dqn_cfg.gamma)
        self._mlp = MLPBackward(self.q_net) if isinstance(self.q_net, MLPQNetwork) and dqn_cfg.loss == "mse" else None
        # detached views of the MLP's weights (no autograd, no no_grad context on the hot path):
        # the target network's for the TD targets, the online network's for acting (CPU)
        flat_mlp = isinstance(self.q_net, MLPQNetwork) and len(self.obs_shape) == 1 and self.obs_dtype == np.float32
        self._target_layers = detached_layers(self.target_net) if flat_mlp else None
        self._online_layers = detached_layers(self.q_net) if flat_mlp else None
        self._act_layers = self._online_layers if self._on_cpu else None
        self._inv_batch = torch.ones((), device=self.device).div(dqn_cfg.batch_size)  # mean's backward: 1/B
        self._grad_out = torch.zeros(dqn_cfg.batch_size, self.n_actions, device=self.device)
        self.epsilon_schedule = LinearSchedule(dqn_cfg.epsilon_start, dqn_cfg.epsilon_end, dqn_cfg.epsilon_decay_steps)

        #: mask mode of a safety shield: next observations (batch) -> bool (batch, n_actions), the actions
        #: allowed in s'; the target's max then runs over those only (der_ros.safety.observation_mask).
        #: None (the default): the plain max of eq. 1, bit-identical to an agent without the attribute.
        self.target_mask: Callable[[np.ndarray], np.ndarray] | None = None
        #: environment steps observed (drives epsilon, learning_starts and train_freq)
        self.steps = 0
        #: gradient steps taken (drives the target-network update)
        self.grad_steps = 0
        self._last_learn_step = -1

    # ------------------------------------------------------------------ acting
    @property
    def epsilon(self) -> float:
        """Exploration rate at the current step (linear decay, see :mod:`der_ros.agent.schedules`)."""
        return self.epsilon_schedule.value(self.steps)

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        """Q(s, .) of one observation (no gradient), as float32 numpy."""
        with torch.inference_mode():
            x = torch.from_numpy(np.asarray(obs, dtype=self.obs_dtype)).unsqueeze(0).to(self.device)
            return self.q_net(x)[0].cpu().numpy()

    def act(self, obs: np.ndarray, explore: bool = True, mask: np.ndarray | None = None) -> int:
        """Epsilon-greedy action: uniform random with probability epsilon, else argmax_a Q(obs, a).

        ``mask`` (a safety shield in mask mode, :mod:`der_ros.safety.apply`): bool per action; both the
        random and the greedy choice are then over the allowed actions only. None: every action, and
        the same random draws as without the argument.
        """
        eps = self.epsilon if explore else self.cfg.eval_epsilon
        if mask is not None:
            allowed = np.flatnonzero(np.asarray(mask, dtype=bool))
            if allowed.size == 0:
                raise ValueError("act(): the action mask allows no action")
            if eps > 0.0 and self.rng.random() < eps:
                return int(allowed[self.rng.integers(allowed.size)])
            q = self.q_values(obs)
            return int(allowed[int(np.argmax(q[allowed]))])
        if eps > 0.0 and self.rng.random() < eps:
            return int(self.rng.integers(self.n_actions))
        if self._act_layers is not None:  # the same forward as q_net's, on detached views of its weights
            x = torch.from_numpy(np.asarray(obs, dtype=np.float32)).unsqueeze(0)
            return int(mlp_forward(x, self._act_layers).argmax(1).item())
        with torch.inference_mode():
            x = torch.from_numpy(np.asarray(obs, dtype=self.obs_dtype)).unsqueeze(0).to(self.device)
            return int(self.q_net(x).argmax(1).item())

    def observe(
        self,
        obs: np.ndarray,
        action: int,
        reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        truncated: bool,
    ) -> None:
        """Store one transition (s, a, r, s', terminated, truncated) and count one environment step."""
        self.replay.add(obs, action, reward, next_obs, terminated, truncated)
        self.steps += 1

    def observe_deferred(self, obs: np.ndarray, action: int, complete: Callable[[], tuple[Any, ...]]) -> None:
        """:meth:`observe` for a step still being simulated: ``complete()`` returns ``(reward, next_obs,
        terminated, truncated)`` when the replay first needs them (``ReplayBuffer.add_deferred``), so a
        :meth:`learn` call in between takes the same gradient step as after :meth:`observe`."""
        self.replay.add_deferred(obs, action, complete)
        self.steps += 1

    # ---------------------------------------------------------------- learning
    def learning_due(self) -> bool:
        """True when gradient steps are due at the current environment step.

        Due when more than ``learning_starts`` steps were observed, the step count is a multiple
        of ``train_freq``, the replay can fill a batch, and this step has not been trained yet
        (so calling :meth:`learn` twice per environment step does not double the updates).
        """
        c = self.cfg
        return (
            self.steps > c.learning_starts
            and self.steps % c.train_freq == 0
            and self._last_learn_step != self.steps
            and len(self.replay) >= c.batch_size
        )

    def learn(self) -> dict[str, float]:
        """Run ``gradient_steps`` updates when due; return metrics (empty dict when nothing was due).

        Metric names are stable: ``losses/td_loss``, ``losses/q_values`` (mean Q(s, a) of the
        batch), ``losses/abs_td_error`` (mean |delta|, the trace of Fig. 2a), ``charts/epsilon``,
        ``charts/gradient_steps``. The replay's gauges are not in it: ``replay.stats()`` gives them
        when they are logged (every caller snapshots them there; computing them at every step, a
        pass over H2's weights, cost ~3% of the step).
        """
        if not self.learning_due():
            return {}
        self._last_learn_step = self.steps
        n = self.cfg.gradient_steps
        loss_sum = q_sum = abs_td_sum = 0.0
        for _ in range(n):
            loss, q_mean, abs_td = self._gradient_step()
            loss_sum += loss
            q_sum += q_mean
            abs_td_sum += abs_td
        metrics = {
            "losses/td_loss": loss_sum / n,
            "losses/q_values": q_sum / n,
            "losses/abs_td_error": abs_td_sum / n,
            "charts/epsilon": self.epsilon,
            "charts/gradient_steps": float(self.grad_steps),
        }
        return metrics

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(array))  # no copy
        return t if self._on_cpu else t.to(self.device, non_blocking=True)

    def td_targets(self, rewards: torch.Tensor, next_obs: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
        """y = r + gamma * (1 - terminated) * V_target(s') (eq. 1); truncation never cuts the bootstrap."""
        return self._targets(rewards, next_obs, self.cfg.gamma * (1.0 - terminated.float()))

    def _targets(
        self, rewards: torch.Tensor, next_obs: torch.Tensor, discount: torch.Tensor, forbid: torch.Tensor | None = None
    ) -> torch.Tensor:
        """y = r + discount * V_target(s'), ``discount`` = gamma, or 0 where the episode terminated.

        ``forbid`` (bool, batch x actions; mask mode of a shield): actions not allowed in s' are left
        out of the max (and of double DQN's online argmax).
        """
        if self._target_layers is not None:  # the MLP on detached weights: the same kernels, no autograd
            next_q = mlp_forward(next_obs, self._target_layers)
            if forbid is not None:
                next_q = next_q.masked_fill(forbid, -math.inf)
            if self.cfg.double_dqn:
                online = mlp_forward(next_obs, self._online_layers)  # type: ignore[arg-type]
                if forbid is not None:
                    online = online.masked_fill(forbid, -math.inf)
                next_v = next_q.gather(1, online.argmax(1, keepdim=True)).squeeze(1)
            else:
                next_v = next_q.amax(1)
            return rewards + discount * next_v
        with torch.no_grad():
            next_q = self.target_net(next_obs)
            if forbid is not None:
                next_q = next_q.masked_fill(forbid, -math.inf)
            if self.cfg.double_dqn:
                online = self.q_net(next_obs)
                if forbid is not None:
                    online = online.masked_fill(forbid, -math.inf)
                next_v = next_q.gather(1, online.argmax(1, keepdim=True)).squeeze(1)
            else:
                next_v = next_q.amax(1)
            return rewards + discount * next_v

    def gradient_step(self) -> tuple[float, float, float]:
        """One update now, ignoring the schedule (offline training from recorded transitions).

        Returns (TD loss, mean Q(s, a), mean |delta|) of the batch.
        """
        if len(self.replay) < self.cfg.batch_size:
            raise ValueError(
                f"replay holds {len(self.replay)} transitions, fewer than batch_size {self.cfg.batch_size}"
            )
        return self._gradient_step()

    def _gradient_step(self) -> tuple[float, float, float]:
        """Sample, eq. 1/2 loss, gradient, clipping, Adam, target update, priorities back to the replay.

        With the MLP and the squared loss the gradient is computed by :class:`MLPBackward`
        (autograd's own kernels, without autograd's bookkeeping; bit-identical results), else by
        autograd. Both paths give the same numbers (``test/agent/test_agent.py`` checks them against a
        plain autograd step).
        """
        batch = self.replay.sample(self.cfg.batch_size)
        obs = self._tensor(batch.obs)
        next_obs = self._tensor(batch.next_obs)
        actions = self._tensor(batch.actions.astype(np.int64, copy=False)).unsqueeze(1)
        rewards = self._tensor(batch.rewards.astype(np.float32, copy=False))
        if self.cfg.reward_scale != 1.0:
            rewards = rewards * self.cfg.reward_scale
        # gamma * (1 - terminated) as float32, the values torch computes for it, in one numpy call
        discount = self._tensor(np.where(batch.terminated, np.float32(0.0), self._gamma32))
        # a replay that does not declare itself unweighted (importance_weighted False) is taken as weighted
        weighted = getattr(self.replay, "importance_weighted", True)
        weights = self._tensor(batch.weights.astype(np.float32, copy=False)) if weighted or self._mlp is None else None

        forbid = None
        if self.target_mask is not None:  # mask mode: the max over the actions allowed in s'
            allowed = np.asarray(self.target_mask(batch.next_obs), dtype=bool)
            forbid = self._tensor(~allowed)
        y = self._targets(rewards, next_obs, discount, forbid)
        if self._mlp is not None:
            q = self._mlp.forward(obs).gather(1, actions).squeeze(1)
            td = y - q  # delta of eq. 2
            # d loss / d q in the order autograd evaluates it: mean (1/B), weights, square (2 delta), minus;
            # without importance weights (all 1.0) both products by them are skipped: x * 1.0 == x exactly
            if weighted:
                loss = (weights * td.square()).mean()
                grad_q = (self._inv_batch * weights) * (td * -2.0)
            else:
                loss = td.square().mean()
                grad_q = self._inv_batch * (td * -2.0)
            self._mlp.backward(self._grad_out.zero_().scatter_add_(1, actions, grad_q.unsqueeze(1)))
        else:
            q = self.q_net(obs).gather(1, actions).squeeze(1)
            td = y - q
            if self.cfg.loss == "mse":
                per_sample = td.square()
            else:
                per_sample = F.smooth_l1_loss(q, y, reduction="none")
            loss = (weights * per_sample).mean()
            self._flat_grad.zero_()
            loss.backward()
            q, td, loss = q.detach(), td.detach(), loss.detach()
        loss_value = float(loss.item())
        if not math.isfinite(loss_value):  # checked before the optimizer moves a weight
            raise self._diverged(f"TD loss = {loss_value}")
        if self.cfg.max_grad_norm > 0.0:
            self._clip_gradient()
        elif not bool(torch.isfinite(self._flat_grad).all()):
            raise self._diverged("a non-finite gradient")
        self.optimizer.step()
        self.grad_steps += 1
        if self.grad_steps % self.cfg.target_update_interval == 0:
            self.update_target()

        td_np = td.cpu().numpy().astype(np.float32, copy=False)
        self.replay.update_priorities(batch.indices, td_np)
        n = td_np.shape[0]
        q_sum = float(np.add.reduce(q.cpu().numpy()))  # (np.mean costs ~4x more per call)
        return loss_value, q_sum / n, float(np.add.reduce(np.abs(td_np))) / n

    def _diverged(self, what: str) -> LearnerDiverged:
        return LearnerDiverged(
            f"the learner diverged at gradient step {self.grad_steps + 1} (env step {self.steps}): {what}; the step "
            "was not taken, the weights are the last finite ones"
        )

    def parameters_finite(self) -> bool:
        """True when every weight of the online and target networks is finite (one flat buffer each)."""
        return bool(torch.isfinite(self._flat).all()) and bool(torch.isfinite(self._target_flat).all())

    def _clip_gradient(self) -> None:
        """Scale the gradient to global norm ``max_grad_norm`` if it is larger.

        Global norm over all parameters = norm of the one flat gradient buffer. The factor is
        ``min(max_norm / (norm + 1e-6), 1)`` computed in float32 exactly as torch evaluates it on
        a 0-d tensor (``max_norm / t`` is ``t.reciprocal() * max_norm``), but as numpy scalars:
        four tensor operations fewer, and none at all when no clipping is needed.
        """
        norm = np.float32(torch.linalg.vector_norm(self._flat_grad).item())
        if not math.isfinite(norm):  # a non-finite gradient: the step is refused, no weight moves
            raise self._diverged(f"gradient norm = {float(norm)}")
        coef = (np.float32(1.0) / (norm + np.float32(1e-6))) * np.float32(self.cfg.max_grad_norm)
        if coef < 1.0:
            self._flat_grad.mul_(float(coef))

    @torch.no_grad()
    def update_target(self) -> None:
        """Hard copy (tau = 1) or Polyak step target <- tau * online + (1 - tau) * target."""
        if self.cfg.tau >= 1.0:
            self._target_flat.copy_(self._flat)
        else:
            self._target_flat.lerp_(self._flat, self.cfg.tau)

    # ------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue training exactly: nets, optimizer, replay, RNGs, counters.

        Tensors and arrays are the live objects (not copies): serialise (``save``) or deep-copy the
        result before training on.
        """
        return {
            "version": CHECKPOINT_VERSION,
            "obs_shape": list(self.obs_shape),
            "obs_dtype": self.obs_dtype.str,
            "n_actions": self.n_actions,
            "seed": self.seed,
            "dqn_cfg": to_dict(self.cfg),
            "replay_cfg": to_dict(self.replay_cfg),
            "q_net": self.q_net.state_dict(),
            "target_net": self.target_net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "replay": self.replay.state_dict(),
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "steps": self.steps,
            "grad_steps": self.grad_steps,
            "last_learn_step": self._last_learn_step,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict` (shapes and configs must match this agent)."""
        version = state.get("version")
        if version != CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version = {version!r}, expected {CHECKPOINT_VERSION}")
        if tuple(state["obs_shape"]) != self.obs_shape or int(state["n_actions"]) != self.n_actions:
            raise ValueError(
                f"checkpoint is for obs_shape {tuple(state['obs_shape'])}, n_actions {state['n_actions']}; "
                f"this agent has {self.obs_shape}, {self.n_actions}"
            )
        self.q_net.load_state_dict(state["q_net"])
        self.target_net.load_state_dict(state["target_net"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.replay.load_state_dict(_unpack_arrays(state["replay"]))
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.steps = int(state["steps"])
        self.grad_steps = int(state["grad_steps"])
        self._last_learn_step = int(state["last_learn_step"])

    def save(self, path: str | os.PathLike[str], extra: dict[str, Any] | None = None) -> Path:
        """Write a checkpoint atomically (temp file in the same folder, then ``os.replace``).

        ``extra`` (e.g. the training runner's counters and environment state) is stored beside the
        agent under the key ``"extra"``; read it back with :func:`read_checkpoint`.
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        state = self.state_dict()
        state["replay"] = _pack_arrays(state["replay"])
        payload = {"agent": state, "extra": extra or {}}
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        try:
            with open(tmp, "wb") as fh:
                torch.save(payload, fh, pickle_protocol=4)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return path

    @classmethod
    def from_state_dict(cls, state: dict[str, Any], device: str | torch.device = "cpu") -> DQNAgent:
        """Build an agent from the configs stored in ``state`` and load it."""
        dqn_cfg = from_dict(DQNConfig, state["dqn_cfg"], source="checkpoint [dqn_cfg]")
        replay_cfg = from_dict(ReplayConfig, state["replay_cfg"], source="checkpoint [replay_cfg]")
        agent = cls(
            tuple(state["obs_shape"]),
            np.dtype(state["obs_dtype"]),
            int(state["n_actions"]),
            dqn_cfg,
            replay_cfg,
            seed=int(state["seed"]),
            device=device,
        )
        agent.load_state_dict(state)
        return agent

    @classmethod
    def load(cls, path: str | os.PathLike[str], device: str | torch.device = "cpu") -> DQNAgent:
        """Load an agent written by :meth:`save` (also a ``der train`` checkpoint)."""
        return cls.from_state_dict(read_checkpoint(path, device)["agent"], device=device)


def _pack_arrays(state: dict[str, Any]) -> dict[str, Any]:
    """Numeric numpy arrays -> zero-copy torch tensors, which torch.save streams as storages.

    Pickled in-band, a numpy array is first copied into torch.save's in-memory pickle: for the
    2.8 GB Atari replay that would be one more full copy at every checkpoint.
    """
    tensors: dict[str, torch.Tensor] = {}
    other: dict[str, Any] = {}
    for key, value in state.items():
        if isinstance(value, np.ndarray) and value.dtype.kind in "biuf" and value.dtype != np.uint16:
            tensors[key] = torch.from_numpy(value if value.flags.c_contiguous else value.copy())
        else:
            other[key] = value
    return {"__packed__": True, "tensors": tensors, "other": other}


def _unpack_arrays(state: dict[str, Any]) -> dict[str, Any]:
    if not state.get("__packed__"):
        return state
    out = dict(state["other"])
    out.update({k: t.cpu().numpy() for k, t in state["tensors"].items()})
    return out


def read_checkpoint(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> dict[str, Any]:
    """The raw checkpoint mapping ``{"agent": ..., "extra": ...}`` (our own files: full unpickling)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    return torch.load(path, map_location=resolve_device(device), weights_only=False)
