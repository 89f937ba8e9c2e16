"""``der train``: train one DQN agent with uniform / PER / DER replay on one environment.

Examples::

    der train --config config/cartpole.yaml --replay der --lam 0.9 --seed 3
    der train --config config/atari.yaml --env-id ALE/Breakout-v5 --steps 200000 --device auto
    der train --config config/cartpole.yaml --set agent.hidden_sizes=[256,256] --agent-lr 1e-3
    der train --resume runs/CartPole-v1-der0.9-3-.../checkpoint.pt

Precedence: YAML file < per-field flags (``--agent-lr``, ``--replay-kind``, ``--train-log-interval``
...) < short flags (``--replay``, ``--lam``, ``--seed``, ``--steps``, ``--device``, ``--run-dir``)
< ``--set section.key=value``. Everything is validated before training starts; errors name the
file (or the command line), the section, the key and the value.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from der_ros.configuration import ConfigError, add_dataclass_arguments, field_specs
from der_ros.safety.config import SAFETY_KINDS, SAFETY_MODES
from der_ros.train.config import (
    SECTIONS,
    ExperimentConfig,
    add_set_argument,
    apply_dotted_overrides,
    experiment_from_dict,
    load_experiment_config,
)

__all__ = ["add_arguments", "run", "config_from_args"]

log = logging.getLogger(__name__)

#: short flag dest -> dotted config key
SHORT_FLAGS = {
    "replay": "replay.kind",
    "lam": "replay.lam",
    "seed": "train.seed",
    "steps": "train.total_steps",
    "device": "train.device",
    "run_dir": "train.run_dir",
    "safety": "env.safety.kind",
    "safety_mode": "env.safety.mode",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None, help="training YAML (sections env, agent, replay, train)")
    parser.add_argument("--replay", choices=("uniform", "per", "der"), default=None, help="replay kind")
    parser.add_argument("--lam", type=float, default=None, help="DER: fraction of each batch drawn from H2 (lambda)")
    parser.add_argument("--seed", type=int, default=None, help="run seed")
    parser.add_argument("--steps", type=int, default=None, help="total environment steps")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None, help="torch device")
    parser.add_argument(
        "--run-dir", dest="run_dir", default=None, help="output folder (default runs/<env>-<replay>-<seed>-<time>)"
    )
    parser.add_argument("--resume", type=Path, default=None, help="continue from a checkpoint.pt of an earlier run")
    parser.add_argument("--safety", choices=SAFETY_KINDS, default=None,
                        help="the shield in front of the agent (env.safety.kind; docs/safety.md): none, rss or sumo")
    parser.add_argument("--safety-mode", dest="safety_mode", choices=SAFETY_MODES, default=None,
                        help="replace (an unsafe command becomes keep lane) or mask (env.safety.mode)")
    add_set_argument(parser)
    for section, cls in SECTIONS.items():
        group = parser.add_argument_group(f"{section} section (per-field overrides)")
        add_dataclass_arguments(group, cls, prefix=f"{section}_")  # type: ignore[arg-type]


def _overrides_from_args(args: argparse.Namespace) -> tuple[dict[str, Any], list[str]]:
    dotted: dict[str, Any] = {}
    for section, cls in SECTIONS.items():
        for spec in field_specs(cls):
            value = getattr(args, f"{section}_{spec.name}", None)
            if value is not None:
                dotted[f"{section}.{spec.name}"] = value
    for dest, key in SHORT_FLAGS.items():
        value = getattr(args, dest, None)
        if value is not None:
            dotted[key] = value
    return dotted, list(args.set_values)


def config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    """Resolve the config: file (or the resumed run's config) + flags + --set, all validated."""
    dotted, set_values = _overrides_from_args(args)
    if args.config is None and args.resume is not None:
        from der_ros.agent.dqn import read_checkpoint

        try:
            ckpt = read_checkpoint(args.resume)
        except FileNotFoundError:
            raise ConfigError(f"--resume {args.resume}: no such checkpoint") from None
        except Exception as exc:  # noqa: BLE001 - torch.load of a file that is not ours
            raise ConfigError(f"--resume {args.resume}: not a der_ros checkpoint ({type(exc).__name__}: {exc})") from None
        extra = ckpt.get("extra") if isinstance(ckpt, dict) else None
        stored = extra.get("config") if isinstance(extra, dict) else None
        if stored is None:
            raise ConfigError(
                f"--resume {args.resume}: the checkpoint holds no training config (der graph's agent node writes none); "
                "pass --config with the environment to continue in, e.g. --config config/ring.yaml")
        data = apply_dotted_overrides(stored, dotted)
        data = apply_dotted_overrides(data, set_values)
        return experiment_from_dict(data, source=f"{args.resume} [config] + command line")
    cfg = load_experiment_config(args.config, dotted)
    if set_values:
        data = apply_dotted_overrides(cfg.to_dict(), set_values)
        cfg = experiment_from_dict(data, source=f"{args.config or 'defaults'} + --set")
    return cfg


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    import torch

    if cfg.train.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("train.device = 'cuda', but CUDA is not available on this machine (use auto or cpu)")
    from der_ros.train.runner import train

    run_dir = cfg.train.run_dir
    if run_dir is None and args.resume is not None and (Path(args.resume).parent / "config.yaml").is_file():
        run_dir = str(Path(args.resume).parent)  # a der train run continues in its own directory
    summary = train(cfg, run_dir=run_dir, resume=args.resume)
    print(
        f"run {summary.run_dir}: {summary.steps} steps, {summary.episodes} episodes, "
        f"mean return {summary.mean_return:.2f}, max MA20 {summary.max_ma20_return:.2f}, "
        f"{summary.steps_per_s:.0f} steps/s" + (" (interrupted)" if summary.interrupted else "")
    )
    if summary.checkpoint:
        print(f"checkpoint: {summary.checkpoint}")
    return 130 if summary.interrupted else 0
