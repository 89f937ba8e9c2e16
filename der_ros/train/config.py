"""Training configs: EnvConfig, TrainConfig and the four-section YAML layout.

A training YAML file has up to four top-level sections, each loaded into its own dataclass::

    env:    EnvConfig     which environment and its preprocessing
    agent:  DQNConfig     learner hyperparameters (der_ros.agent.config)
    replay: ReplayConfig  replay kind and sizes (der_ros.replay.config)
    train:  TrainConfig   steps, seed, logging, checkpoints, run directory

Unknown sections or keys, wrong types and out-of-range values raise :class:`ConfigError` naming
the file, the section, the key and the value, before anything starts.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from der_ros.agent.config import DQNConfig
from der_ros.configuration import ConfigError, from_dict, param, read_yaml_mapping, reject_unknown_keys, to_dict
from der_ros.replay.config import ReplayConfig
from der_ros.safety.config import SafetyConfig
from der_ros.yaml_loader import YamlError, excerpt, load_yaml_text

#: upper bound of train.num_envs: a process and a simulation each; more than this is a typo, not a machine
MAX_NUM_ENVS = 64

__all__ = [
    "EnvConfig",
    "TrainConfig",
    "ExperimentConfig",
    "SECTIONS",
    "load_experiment_config",
    "experiment_from_dict",
    "apply_dotted_overrides",
    "parse_assignments",
    "add_set_argument",
    "save_experiment_config",
]


@dataclass
class EnvConfig:
    """Which environment to train on, and the Atari preprocessing (ignored for other ids)."""

    id: str = param(
        "CartPole-v1",
        "gymnasium id: 'CartPole-v1', an Atari id ('ALE/Breakout-v5', 'BreakoutNoFrameskip-v4'), "
        "or a 'der_ros/...' SUMO id (registered by importing sumo_bridge)",
    )
    max_episode_steps: int | None = param(None, "override the env's time limit (None = the registered one)", low=1)
    frame_skip: int = param(4, "Atari: repeat each action this many frames (max-pooled over the last two)", low=1)
    frame_stack: int = param(4, "Atari: stack this many preprocessed frames (paper: 84x84x4 input)", low=1)
    screen_size: int = param(84, "Atari: frames are resized to screen_size x screen_size grey images", low=8)
    noop_max: int = param(30, "Atari: up to this many no-op actions at reset (random start)", low=0)
    terminal_on_life_loss: bool = param(
        False,
        "Atari: signal terminated=True to the learner when a life is lost; the game itself continues "
        "(episode returns are still whole-game scores)",
    )
    clip_rewards: bool = param(True, "Atari: clip rewards given to the learner to [-1, 1] (scores stay raw)")
    sticky_action_prob: float = param(
        0.0,
        "Atari: probability of repeating the previous action (0 = the classic DQN protocol, "
        "NoFrameskip-v4 style; 0.25 = ALE v5 default)",
        low=0.0,
        high=1.0,
    )
    kwargs: dict = param(
        default_factory=dict, help="extra keyword arguments for gymnasium.make (e.g. a SUMO scenario's settings)"
    )
    safety: SafetyConfig = param(
        default_factory=SafetyConfig,
        help="the shield between the agent and a lane-change env (docs/safety.md); kind 'none' leaves the env as is",
    )

    def check(self) -> None:
        if not isinstance(self.kwargs, dict):
            raise ConfigError(f"kwargs = {self.kwargs!r}, expected a mapping of gymnasium.make keyword arguments")
        if self.safety.enabled and not self.id.startswith("der_ros/"):
            raise ConfigError(f"safety.kind = {self.safety.kind!r} needs a lane-change env ('der_ros/...'), "
                              f"env.id is {self.id!r}")  # fmt: skip


@dataclass
class TrainConfig:
    """One training run: how long, which seed, where to write, how often to log and checkpoint."""

    total_steps: int = param(10_000, "environment steps to train for (paper: 10,000 CartPole, >= 200,000 Atari)", low=1)
    seed: int = param(
        0,
        "seed of the environment, the exploration and the replay sampling (below 1000000000: higher seeds are "
        "evaluation seeds)",
        low=0,
        high=999_999_999,
    )
    device: str = param("auto", "torch device: auto (cuda when present), cpu or cuda", choices=("auto", "cpu", "cuda"))
    threads: int = param(1, "torch intra-op threads (1 is fastest for small networks and fair on shared cores)", low=1)
    env_process: bool | None = param(
        None,
        "step the environment in its own process while the learner runs its gradient step (about max(env, "
        "learner) per step on two cores instead of their sum), with the same results as the sequential loop bit "
        "for bit (der_ros/train/env_process.py). None (auto): on for the SUMO environments when this run has a CPU "
        "for the trainer, one for the env and one for periodic evaluations in a process (the cores of the "
        "process, or $DER_CPUS_PER_RUN, which the suites' backends set to their share per run) and the run has "
        "5,000 steps or more, off otherwise; "
        "False: act, step, observe, learn in turn in this process",
    )
    num_envs: int = param(
        1,
        "environment workers feeding the one learner, one process each, one gradient step per decision overall "
        "(der_ros/train/env_pool.py). 1 (default): one environment, the loop and results of before. N > 1: worker j's "
        "env seeded from train.seed and j, transitions learnt round robin, actions from the network of up to 32 "
        "rounds ago; more decisions per wall second, the same replay ratio, a different (deterministic) run",
        low=1,
        high=MAX_NUM_ENVS,
    )
    run_dir: str | None = param(None, "output folder; None = runs/<env>-<replay>-<seed>-<timestamp> under runs_root")
    runs_root: str = param("runs", "parent folder of generated run directories")
    log_interval: int = param(
        100, "write averaged training metrics (losses/*, replay/*, charts/*) every this many env steps", low=1
    )
    checkpoint_interval: int = param(
        0, "write runs/.../checkpoint.pt every this many env steps (0 = only at the end and on Ctrl-C)", low=0
    )
    eval_interval: int = param(
        0,
        "greedy evaluation (epsilon = 0, on held-out evaluation seeds) at step 0 and every this many env "
        "steps (0 = only the final one); results in evaluations.csv and the eval/* metrics",
        low=0,
    )
    eval_episodes: int = param(100, "episodes per periodic evaluation", low=1)
    final_eval_episodes: int = param(
        300, "episodes of the evaluation at the end of training (evaluation.json; 0 = none)", low=0
    )
    eval_episodes_per_seed: int = param(
        1,
        "evaluation episodes per seeded reset: 1 = every episode on its own seed; n > 1 = streams of a "
        "seeded reset and n - 1 unseeded ones (urban: a seeded reset costs a 150 s traffic warm-up)",
        low=1,
    )
    eval_seed_base: int = param(
        1_000_000_000,
        "first evaluation seed: 1000000000 = the report set, 1500000000 = the tuning set (every choice of "
        "settings is made on tuning seeds); training seeds must stay below 1000000000",
        choices=(1_000_000_000, 1_500_000_000),
    )
    eval_mode: str = param(
        "auto",
        "where evaluations run: 'process' (a second process with its own env; training goes on meanwhile), "
        "'inline' (in the training process, several envs in lockstep), 'auto' (process for SUMO envs, whose "
        "libsumo allows one simulation per process; inline otherwise)",
        choices=("auto", "process", "inline"),
    )
    tensorboard: bool = param(True, "also write TensorBoard event files (metrics.csv is always written)")
    progress: bool = param(True, "show a progress bar (only on a terminal)")
    save_final_checkpoint: bool = param(True, "write checkpoint.pt when training ends")


SECTIONS: dict[str, type] = {"env": EnvConfig, "agent": DQNConfig, "replay": ReplayConfig, "train": TrainConfig}


@dataclass
class ExperimentConfig:
    """All four sections of a training YAML file."""

    env: EnvConfig = field(default_factory=EnvConfig)
    agent: DQNConfig = field(default_factory=DQNConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {name: to_dict(getattr(self, name)) for name in SECTIONS}


def experiment_from_dict(data: dict[str, Any] | None, source: str = "config") -> ExperimentConfig:
    """Build an :class:`ExperimentConfig` from ``{section: {key: value}}``; unknown sections are errors."""
    data = dict(data or {})
    reject_unknown_keys(data, SECTIONS, source, what="section", known_as="known sections")
    parts = {}
    for name, cls in SECTIONS.items():
        section = data.get(name) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{source}: section {name!r} = {section!r}, expected a mapping")
        parts[name] = from_dict(cls, section, source=f"{source} [{name}]")
    agent, replay = parts["agent"], parts["replay"]
    if agent.batch_size > replay.capacity:  # the learner could never draw a batch
        raise ConfigError(f"{source} [agent]: batch_size = {agent.batch_size}, expected <= replay.capacity "
                          f"({replay.capacity})", key="agent.batch_size", value=agent.batch_size,
                          reason=f"expected <= replay.capacity ({replay.capacity})")
    train = parts["train"]
    if train.num_envs > 1 and train.env_process is False:
        raise ConfigError(f"{source} [train]: num_envs = {train.num_envs} runs each env in a worker process, "
                          "expected env_process unset or true", key="train.num_envs", value=train.num_envs,
                          reason="expected env_process unset or true")
    env = parts["env"]
    if train.num_envs > 1 and env.safety.enabled:  # the pool's workers would store the proposal, not the applied action
        raise ConfigError(f"{source} [train]: num_envs = {train.num_envs} with env.safety.kind = "
                          f"{env.safety.kind!r}: the shield runs with one environment (num_envs 1) only",
                          key="train.num_envs", value=train.num_envs, reason="expected 1 with a shield")
    return ExperimentConfig(**parts)


def parse_assignments(
    texts: Iterable[str], source: str = "command line", label: str = "override"
) -> list[tuple[str, Any]]:
    """``["section.key=yaml-value", ...]`` -> ``[("section.key", value), ...]`` (values parsed as YAML).

    Errors name ``source`` and ``label`` (e.g. ``"command line: --set 'x', expected section.key=value"``).
    """
    items: list[tuple[str, Any]] = []
    for text in texts:
        if "=" not in text:
            raise ConfigError(f"{source}: {label} {text!r}, expected section.key=value")
        key, raw = text.split("=", 1)
        try:
            value = load_yaml_text(raw, f"{source}: {label} {excerpt(key.strip())}")
        except YamlError as exc:
            raise ConfigError(str(exc)) from None
        items.append((key.strip(), value))
    return items


def add_set_argument(parser: Any, help: str = "override any config field; VALUE is YAML (repeatable)") -> None:
    """The repeatable ``--set SECTION.KEY=VALUE`` flag (collected in ``args.set_values``)."""
    parser.add_argument(
        "--set",
        dest="set_values",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help=help,
    )


def apply_dotted_overrides(
    data: dict[str, Any], overrides: dict[str, Any] | list[str], source: str = "command line"
) -> dict[str, Any]:
    """Apply ``{"section.key": value}`` (or ``["section.key=yaml-value", ...]``) to a raw config mapping.

    Values given as strings are parsed as YAML (``--set agent.hidden_sizes=[256,256]``). Unknown
    sections and keys are reported by the later validation, naming ``source``.
    """
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    items = list(overrides.items()) if isinstance(overrides, dict) else parse_assignments(overrides, source)
    for key, value in items:
        if value is None and isinstance(overrides, dict):
            continue
        if "." not in key:
            raise ConfigError(
                f"{source}: override key {key!r} = {value!r}, expected section.key (sections: {', '.join(SECTIONS)})"
            )
        section, name = key.split(".", 1)
        if section not in SECTIONS:
            raise ConfigError(
                f"{source}: unknown section {section!r} in {key!r} = {value!r}; known: {', '.join(SECTIONS)}"
            )
        sec = out.setdefault(section, {})
        if not isinstance(sec, dict):
            raise ConfigError(f"{source}: section {section!r} is not a mapping")
        head, _, rest = name.partition(".")
        if rest and isinstance(sec.get(head, {}), dict):  # inside a mapping-valued key: env.kwargs.scenario.time_aware
            sec[head] = dict(sec.get(head, {}))  # (absent: a new mapping, e.g. env.safety.kind without a safety section)
            node = sec[head]
            parts = rest.split(".")
            for part in parts[:-1]:
                child = node.get(part, {})
                if not isinstance(child, dict):
                    raise ConfigError(f"{source}: {key!r} = {value!r}: {section}.{head}.{part} = {child!r} is not a "
                                      "mapping")
                node[part] = dict(child)
                node = node[part]
            node[parts[-1]] = value
            continue
        sec[name] = value
    return out


def load_experiment_config(
    path: str | Path | None, overrides: dict[str, Any] | list[str] | None = None
) -> ExperimentConfig:
    """Load a training YAML file (or the defaults when ``path`` is None) and apply overrides.

    The file is validated on its own first, so an error in the file names the file; then the
    overrides are applied and validated again, naming the command line.
    """
    if path is None:
        data: dict[str, Any] = {}
        source = "defaults"
    else:
        path = Path(path)
        data = read_yaml_mapping(path, expected="a mapping of sections")
        source = str(path)
    experiment_from_dict(data, source=source)  # errors in the file itself name the file
    if overrides:
        data = apply_dotted_overrides(data, overrides)
        return experiment_from_dict(data, source=f"{source} + command line")
    return experiment_from_dict(data, source=source)


def save_experiment_config(cfg: ExperimentConfig, path: str | Path) -> None:
    """Write the resolved config as YAML (atomically), in the same four-section layout."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    tmp.replace(path)
