"""Where ``der train --resume`` continues from: its own checkpoints, or one of ``der graph``'s agent node.

Both are :meth:`der_ros.agent.dqn.DQNAgent.save` files with the same agent state (networks,
optimizer, replay contents, RNGs, step counters, and the agent and replay configs that state
was built with). They differ in ``extra``:

* ``der train``'s ``checkpoint.pt`` also holds the runner (episode count, returns, metrics
  accumulator, current observation), the pickled environment when it can be, and the run's
  four-section config;
* the agent node's ``checkpoint_out`` holds only the node's ``online/`` counters -- the node
  has no environment and no training config (its environment is the bridge).

A node checkpoint resumes the *same learner* in the simulator environment of ``--config``: its
agent and replay configs replace the file's ``agent`` and ``replay`` sections (they describe
the replay state it carries; differences are logged in one line), the ``env`` and ``train``
sections come from the file, and the runner starts a new episode (seeded from the step count)
with its own episode count. It is refused with one sentence (:class:`ConfigError`) when the
environment's observation shape or action count is not the checkpoint's, when its weights are
not finite, or when the file is not a checkpoint at all -- never a ``KeyError``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from der_ros.agent.config import DQNConfig
from der_ros.agent.dqn import CHECKPOINT_VERSION, read_checkpoint
from der_ros.configuration import ConfigError, from_dict, to_dict
from der_ros.replay.config import ReplayConfig

__all__ = ["ResumePoint", "load_resume_point"]

log = logging.getLogger(__name__)


@dataclass
class ResumePoint:
    """A checkpoint read for resuming, with what kind of writer it came from."""

    path: Path
    #: the agent's state (``DQNAgent.state_dict`` layout)
    agent_state: dict[str, Any]
    #: ``der train``'s runner state; None for a checkpoint of the agent node
    runner: dict[str, Any] | None
    #: the pickled environment (``der train`` checkpoints of pure-Python envs only)
    env_bytes: bytes | None
    #: the agent / replay configs the checkpoint's state was built with
    agent_cfg: DQNConfig
    replay_cfg: ReplayConfig

    @property
    def from_agent_node(self) -> bool:
        return self.runner is None

    @property
    def steps(self) -> int:
        return int(self.agent_state["steps"])

    def config(self, cfg: Any) -> Any:
        """``cfg`` (an ExperimentConfig) with the checkpoint's agent and replay sections, for a node
        checkpoint (logged when they differ from the file's); ``cfg`` itself otherwise."""
        if not self.from_agent_node:
            return cfg
        changed = [f"{section}.{k}" for section, mine, theirs in (("agent", cfg.agent, self.agent_cfg),
                                                                  ("replay", cfg.replay, self.replay_cfg))
                   for k, v in to_dict(theirs).items() if to_dict(mine).get(k) != v]  # fmt: skip
        if changed:
            log.info("%s was written by der graph's agent node: its agent and replay settings replace the config's "
                     "(%s)", self.path, ", ".join(changed))
        return dataclasses.replace(cfg, agent=self.agent_cfg, replay=self.replay_cfg)


def load_resume_point(
    path: str | Path, obs_shape: tuple[int, ...], n_actions: int, device: str | torch.device = "cpu"
) -> ResumePoint:
    """Read ``path`` and check it can continue in an environment with ``obs_shape`` and ``n_actions``."""
    path = Path(path)
    try:
        ckpt = read_checkpoint(path, device)
    except FileNotFoundError:
        raise ConfigError(f"--resume {path}: no such checkpoint") from None
    except Exception as exc:  # noqa: BLE001 - torch.load of a file that is not ours (any unpickling error)
        raise ConfigError(f"--resume {path}: not a der_ros checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("agent"), dict):
        raise ConfigError(f"--resume {path}: not a der_ros checkpoint (no agent state in it)")
    state, extra = ckpt["agent"], ckpt.get("extra") or {}
    if state.get("version") != CHECKPOINT_VERSION:
        raise ConfigError(f"--resume {path}: checkpoint version {state.get('version')!r}, this der_ros reads "
                          f"version {CHECKPOINT_VERSION}")
    shape, actions = tuple(int(s) for s in state["obs_shape"]), int(state["n_actions"])
    if shape != tuple(obs_shape) or actions != int(n_actions):
        raise ConfigError(
            f"--resume {path}: cannot continue this agent here: it was trained on observations of shape {shape} with "
            f"{actions} actions, and the environment of the config gives {tuple(obs_shape)} with {n_actions}"
        )
    bad = [name for name in ("q_net", "target_net") if not _finite(state[name])]
    if bad:
        raise ConfigError(f"--resume {path}: the checkpoint's {' and '.join(bad)} weights are not finite (a diverged "
                          "learner); resume from an earlier checkpoint")
    agent_cfg = from_dict(DQNConfig, state["dqn_cfg"], source=f"{path} [dqn_cfg]")
    replay_cfg = from_dict(ReplayConfig, state["replay_cfg"], source=f"{path} [replay_cfg]")
    runner = extra.get("runner")
    if runner is not None and not isinstance(runner, dict):
        raise ConfigError(f"--resume {path}: its runner state is {type(runner).__name__}, expected a mapping")
    return ResumePoint(path, state, runner, extra.get("env"), agent_cfg, replay_cfg)


def _finite(tensors: dict[str, Any]) -> bool:
    return all(not torch.is_tensor(t) or bool(torch.isfinite(t).all()) for t in tensors.values())
