"""Environment factory: CartPole, Atari with the standard DQN preprocessing, and the SUMO envs.

Every environment comes wrapped in ``RecordEpisodeStatistics`` so the runner reads episode
returns from ``info["episode"]``. For Atari that wrapper sits *below* reward clipping and the
episodic-life signal, so reported returns are raw whole-game scores (what Table 2 compares)
while the learner sees clipped rewards and (optionally) a terminal on each lost life.

Atari stack (paper section 5: grey, 84x84, 4 stacked frames; DQN conventions for the rest)::

    AtariEnv(frameskip=1, repeat_action_probability=sticky)
      -> AtariPreprocessing(noop_max, frame_skip, screen_size, grey, uint8)
      -> RecordEpisodeStatistics
      -> EpisodicLife            (optional: terminated on life loss, game continues on reset)
      -> ClipReward(-1, 1)       (optional)
      -> FrameStackObservation   -> obs (frame_stack, 84, 84) uint8
"""

from __future__ import annotations

import logging
import pickle
from typing import Any

import gymnasium as gym
import numpy as np

import sumo_bridge  # noqa: F401  (registers the der_ros/* SUMO ids with gymnasium)
from der_ros.configuration import ConfigError
from der_ros.safety.wrapper import ShieldWrapper

__all__ = ["make_env", "make_env_from_config", "is_atari_id", "EpisodicLife", "pickle_env_state"]

log = logging.getLogger(__name__)

_ALE_REGISTERED = False


def _register_ale() -> None:
    global _ALE_REGISTERED
    if not _ALE_REGISTERED:
        import ale_py

        gym.register_envs(ale_py)
        _ALE_REGISTERED = True


def is_atari_id(env_id: str) -> bool:
    """True for ids served by ale_py ('ALE/Breakout-v5', 'BreakoutNoFrameskip-v4', ...)."""
    if env_id.startswith("ALE/"):
        return True
    if env_id.startswith("der_ros/"):
        return False
    _register_ale()
    try:
        spec = gym.spec(env_id)
    except gym.error.Error:
        return False
    entry = spec.entry_point if isinstance(spec.entry_point, str) else getattr(spec.entry_point, "__module__", "")
    return "ale_py" in str(entry)


class EpisodicLife(gym.Wrapper):
    """Tell the learner ``terminated=True`` when a life is lost, without restarting the game.

    gymnasium's ``AtariPreprocessing(terminal_on_life_loss=True)`` resets the whole game at the
    next ``reset()``, so the agent would never play with fewer lives. Here ``reset()`` after a
    life loss only takes one no-op step and continues; a real reset happens when the game is over.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._lives = 0
        self._game_over = True

    def _ale_lives(self) -> int:
        return int(self.env.unwrapped.ale.lives())

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._game_over = bool(terminated or truncated)
        lives = self._ale_lives()
        if 0 < lives < self._lives:
            terminated = True
            info = dict(info, life_lost=True)
        self._lives = lives
        return obs, reward, terminated, truncated, info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if self._game_over or seed is not None:
            obs, info = self.env.reset(seed=seed, options=options)
        else:
            obs, _r, terminated, truncated, info = self.env.step(0)
            if terminated or truncated:  # the no-op ended the game: its statistics stay in `info`
                episode = info.get("episode")
                obs, info = self.env.reset(options=options)
                if episode is not None:
                    info = dict(info, episode=episode)
        self._game_over = False
        self._lives = self._ale_lives()
        return obs, info


def make_env(
    env_id: str,
    seed: int,
    *,
    max_episode_steps: int | None = None,
    frame_skip: int = 4,
    frame_stack: int = 4,
    screen_size: int = 84,
    noop_max: int = 30,
    terminal_on_life_loss: bool = False,
    clip_rewards: bool = True,
    sticky_action_prob: float = 0.0,
    **make_kwargs: Any,
) -> gym.Env:
    """Build one environment for ``env_id`` (not yet reset; pass ``seed`` to the first ``reset``).

    The action space is seeded with ``seed``. Atari options are ignored for non-Atari ids;
    ``make_kwargs`` go to ``gymnasium.make``. Ids starting with ``der_ros/`` are the SUMO
    lane-change environments that ``sumo_bridge`` registers (imported with this module).
    """
    time_limit = {"max_episode_steps": max_episode_steps} if max_episode_steps is not None else {}
    if is_atari_id(env_id):
        _register_ale()
        env = gym.make(
            env_id,
            frameskip=1,
            repeat_action_probability=float(sticky_action_prob),
            **time_limit,
            **make_kwargs,
        )
        env = gym.wrappers.AtariPreprocessing(
            env,
            noop_max=noop_max,
            frame_skip=frame_skip,
            screen_size=screen_size,
            terminal_on_life_loss=False,
            grayscale_obs=True,
            scale_obs=False,
        )
        env = gym.wrappers.RecordEpisodeStatistics(env)
        if terminal_on_life_loss:
            env = EpisodicLife(env)
        if clip_rewards:
            env = gym.wrappers.ClipReward(env, -1.0, 1.0)
        env = gym.wrappers.FrameStackObservation(env, frame_stack)
    else:
        env = gym.make(env_id, **time_limit, **make_kwargs)
        env = gym.wrappers.RecordEpisodeStatistics(env)
    if not isinstance(env.action_space, gym.spaces.Discrete):
        raise ValueError(f"env {env_id!r}: action space {env.action_space}, DQN needs Discrete actions")
    env.action_space.seed(int(seed))
    return env


def make_env_from_config(cfg: Any, seed: int) -> gym.Env:
    """:func:`make_env` from an :class:`der_ros.train.config.EnvConfig`.

    An id gymnasium does not know, or keyword arguments its constructor refuses, are a
    :class:`ConfigError` naming ``env.id`` / ``env.kwargs`` (not a gymnasium traceback), so
    ``der train`` can fail before it writes anything.
    """
    try:
        env = make_env(
            cfg.id,
            seed,
            max_episode_steps=cfg.max_episode_steps,
            frame_skip=cfg.frame_skip,
            frame_stack=cfg.frame_stack,
            screen_size=cfg.screen_size,
            noop_max=cfg.noop_max,
            terminal_on_life_loss=cfg.terminal_on_life_loss,
            clip_rewards=cfg.clip_rewards,
            sticky_action_prob=cfg.sticky_action_prob,
            **dict(cfg.kwargs),
        )
    except gym.error.Error as exc:  # NameNotFound, NamespaceNotFound, VersionNotFound, ...
        reason = " ".join(str(exc).split())
        raise ConfigError(f"env.id = {cfg.id!r}: {reason}", key="env.id", value=cfg.id, reason=reason) from None
    except TypeError as exc:  # gymnasium.make passes kwargs to the constructor
        raise ConfigError(f"env.kwargs = {dict(cfg.kwargs)!r}: {exc}", key="env.kwargs", value=dict(cfg.kwargs),
                          reason=str(exc)) from None
    safety = getattr(cfg, "safety", None)
    if safety is not None and safety.enabled:  # the shield (docs/safety.md): outermost, it sees every command
        env = ShieldWrapper(env, safety)
    return env


def obs_spec(env: gym.Env) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of the observations the agent stores."""
    space = env.observation_space
    if not isinstance(space, gym.spaces.Box):
        raise ValueError(f"observation space {space}, expected a Box")
    return tuple(int(s) for s in space.shape), np.dtype(space.dtype)


def pickle_env_state(env: gym.Env) -> bytes | None:
    """The whole environment pickled, for envs whose state is plain Python/numpy (gymnasium's own).

    Others are not pickled even when pickle would not fail: an unpickled ALE env does not continue
    the same frames, and a libsumo env would lose its simulation. Those resume with a new episode.
    """
    module = type(env.unwrapped).__module__
    if not module.startswith("gymnasium.envs.") or getattr(env.unwrapped, "ale", None) is not None:
        return None
    try:
        return pickle.dumps(env, protocol=4)
    except Exception as exc:  # noqa: BLE001 - any env that cannot pickle falls back to a reset
        log.debug("environment state not saved (%s); a resumed run starts a new episode", exc)
        return None
