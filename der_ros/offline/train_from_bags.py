"""``der bag train``: train a DQN from recorded transitions only, then evaluate it in SUMO.

Offline means gradient steps on a replay buffer filled once from the bags' transitions
(:func:`der_ros.offline.export.build_transitions`, the exact observations the online agent saw);
the learner never acts in the environment while training. The replay kind is any of the
online ones (uniform, PER, DER with its lambda): DER's H2 promotion and eq. 3 weights work
the same on a fixed buffer, which is what makes this a cheap way to compare replay kinds on
the same data.

Afterwards the greedy policy runs ``--eval-episodes`` episodes of the scenario, and its
return / success / collision rates are reported beside the online agent's numbers from the
bags (the bridge's episode events).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from der_ros import yaml_loader
from der_ros.agent.config import DQNConfig
from der_ros.bag.reader import BagError, BagReader
from der_ros.configuration import ConfigError, flatten_names, load_yaml, unflatten_names, validate
from der_ros.contract import EPISODE_COLLISION, EPISODE_SUCCESS, EPISODE_TIME_LIMIT
from der_ros.offline.episodes import scan_bag
from der_ros.offline.export import Transitions, build_transitions
from der_ros.replay.config import ReplayConfig
from der_ros.train.envs import make_env
from der_ros.yaml_loader import YamlError
from sumo_bridge import NETWORK_ENV_IDS
from sumo_bridge.observation import ObservationConfig

__all__ = [
    "add_train_arguments",
    "concat_transitions",
    "fill_replay",
    "train_offline",
    "evaluate_policy",
    "online_numbers",
    "run_train",
    "OfflineResult",
]

log = logging.getLogger(__name__)

DEFAULT_ENV = NETWORK_ENV_IDS["ring"]


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bags", type=Path, nargs="+", help="bags whose transitions fill the replay buffer")
    p.add_argument("--replay", choices=("uniform", "per", "der"), default="der", help="replay kind")
    p.add_argument("--lam", type=float, default=None, help="DER lambda (fraction of each batch from H2)")
    p.add_argument("--steps", type=int, default=None, help="gradient steps (default: 2 x transitions)")
    p.add_argument("--batch-size", type=int, default=None, help="batch size (default: DQNConfig's)")
    p.add_argument("--dqn-config", type=Path, default=None, help="YAML of DQNConfig fields")
    p.add_argument("--replay-config", type=Path, default=None, help="YAML of ReplayConfig fields")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env", default=None,
                   help="gymnasium id of the evaluation scenario (default: the recorded scenario from the run's "
                        f"params.yaml beside the bag, else {DEFAULT_ENV})")
    p.add_argument("--eval-episodes", type=int, default=5, help="greedy evaluation episodes (0 = no evaluation)")
    p.add_argument("--max-episode-steps", type=int, default=None, help="time limit of the evaluation episodes")
    p.add_argument("--obs-config", type=Path, default=None, help="YAML of ObservationConfig fields for the export")
    p.add_argument("--save", type=Path, default=None, help="write the trained agent's checkpoint here")
    p.add_argument("--json", action="store_true", help="print the result as one JSON document")
    p.add_argument("--namespace", default=None)


def concat_transitions(parts: list[Transitions]) -> Transitions:
    """Several bags' transitions as one set (episode indices made distinct)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        raise ValueError("no transitions")
    offset = 0
    eps = []
    for p in parts:
        eps.append(p.episode + offset)
        offset += int(p.episode.max()) + 1
    return Transitions(
        obs=np.concatenate([p.obs for p in parts]),
        actions=np.concatenate([p.actions for p in parts]),
        rewards=np.concatenate([p.rewards for p in parts]),
        next_obs=np.concatenate([p.next_obs for p in parts]),
        terminated=np.concatenate([p.terminated for p in parts]),
        truncated=np.concatenate([p.truncated for p in parts]),
        stamps_ns=np.concatenate([p.stamps_ns for p in parts]),
        episode=np.concatenate(eps),
    )


def fill_replay(replay: Any, tr: Transitions) -> None:
    """Add every transition, in recorded order (the order the online agent stored them)."""
    if hasattr(replay, "add_batch"):
        replay.add_batch(tr.obs, tr.actions, tr.rewards, tr.next_obs, tr.terminated, tr.truncated)
        return
    for i in range(len(tr)):
        replay.add(tr.obs[i], int(tr.actions[i]), float(tr.rewards[i]), tr.next_obs[i],
                   bool(tr.terminated[i]), bool(tr.truncated[i]))


def _gradient_step(agent: Any) -> tuple[float, float, float]:
    # The learner's public learn() is paced by environment steps; offline there are none, so
    # call its single-update method directly (public name first if the learner exposes one).
    step = getattr(agent, "gradient_step", None) or agent._gradient_step
    return step()


@dataclass
class OfflineResult:
    agent: Any
    transitions: int
    gradient_steps: int
    train_seconds: float
    final_metrics: dict[str, float]


def make_agent(obs_dim: int, n_actions: int, dqn_cfg: Any, replay_cfg: Any, seed: int) -> Any:
    from der_ros.agent.dqn import DQNAgent  # lazy: torch (``der bag info`` must start fast)

    return DQNAgent((obs_dim,), np.float32, n_actions, dqn_cfg, replay_cfg, seed=seed, device="cpu")


def train_offline(tr: Transitions, dqn_cfg: Any, replay_cfg: Any, steps: int, seed: int = 0,
                  n_actions: int = 3, agent: Any | None = None) -> OfflineResult:
    """Fill the agent's replay with ``tr`` and run ``steps`` gradient steps (no environment)."""
    if len(tr) < dqn_cfg.batch_size:
        raise ValueError(f"{len(tr)} transitions, fewer than the batch size {dqn_cfg.batch_size}")
    if agent is None:
        agent = make_agent(tr.obs.shape[1], n_actions, dqn_cfg, replay_cfg, seed)
    fill_replay(agent.replay, tr)
    t0 = time.perf_counter()
    losses = []
    for _ in range(steps):
        loss, _q, abs_td = _gradient_step(agent)
        losses.append((loss, abs_td))
    metrics: dict[str, float] = {}
    if losses:
        tail = np.asarray(losses[-100:], dtype=np.float64)
        metrics = {"losses/td_loss": float(tail[:, 0].mean()), "losses/abs_td_error": float(tail[:, 1].mean())}
    metrics.update({k: float(v) for k, v in agent.replay.stats().items()})
    return OfflineResult(agent, len(tr), steps, time.perf_counter() - t0, metrics)


def evaluate_policy(agent: Any, env_id: str, episodes: int, seed: int = 0,
                    max_episode_steps: int | None = None, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Greedy episodes in the simulator: mean return and success / collision / time-limit rates."""
    env = make_env(env_id, seed, max_episode_steps=max_episode_steps, **(env_kwargs or {}))
    returns: list[float] = []
    outcomes: list[str] = []
    try:
        for ep in range(episodes):
            obs, info = env.reset(seed=seed + ep)
            ret, done = 0.0, False
            event = None
            while not done:
                a = agent.act(obs, explore=False)
                obs, r, terminated, truncated, info = env.step(a)
                ret += float(r)
                done = bool(terminated or truncated)
                event = info.get("event") if isinstance(info, dict) else None
                if done and event is None:
                    event = EPISODE_TIME_LIMIT if truncated else "terminated"
            returns.append(ret)
            outcomes.append(str(event))
    finally:
        env.close()
    n = max(1, len(returns))
    return {
        "episodes": len(returns),
        "mean_return": float(np.mean(returns)) if returns else None,
        "success_rate": sum(o == EPISODE_SUCCESS for o in outcomes) / n,
        "collision_rate": sum(o == EPISODE_COLLISION for o in outcomes) / n,
        "time_limit_rate": sum(o == EPISODE_TIME_LIMIT for o in outcomes) / n,
        "returns": returns,
        "outcomes": outcomes,
    }


def online_numbers(bags: list[Path], namespace: str | None = None) -> dict[str, Any]:
    """The online agent's episodes in the bags (finished episodes only)."""
    eps = []
    for b in bags:
        eps.extend(e for e in scan_bag(BagReader(b), namespace).episodes if e.outcome != "incomplete")
    n = max(1, len(eps))
    return {
        "episodes": len(eps),
        "mean_return": float(np.mean([e.ret for e in eps])) if eps else None,
        "success_rate": sum(e.outcome == EPISODE_SUCCESS for e in eps) / n if eps else None,
        "collision_rate": sum(e.outcome == EPISODE_COLLISION for e in eps) / n if eps else None,
        "time_limit_rate": sum(e.outcome == EPISODE_TIME_LIMIT for e in eps) / n if eps else None,
    }


def recorded_scenario(bag: Path) -> dict[str, Any] | None:
    """The bridge's ``scenario.*`` parameters from the ``params.yaml`` ``der graph`` writes beside
    the bag (``<run>/params.yaml`` for ``<run>/bag``), as ScenarioConfig fields; None if absent.

    Evaluating on the recorded scenario (network, time limit, traffic, observation scales) is
    what makes the offline numbers comparable with the online ones of the bag.
    """
    bag_dir = bag if bag.is_dir() else bag.parent
    path = bag_dir.parent / "params.yaml"
    if not path.is_file():
        return None
    try:
        params = ((yaml_loader.load_yaml(path) or {}).get("bridge_node") or {}).get("ros__parameters") or {}
    except (YamlError, AttributeError) as exc:
        log.warning("cannot read %s: %s", path, exc)
        return None
    return unflatten_names(flatten_names(params), "scenario") or None


def _configs(args: argparse.Namespace) -> tuple[Any, Any]:
    dqn_cfg = load_yaml(args.dqn_config, DQNConfig) if args.dqn_config else DQNConfig()
    replay_cfg = load_yaml(args.replay_config, ReplayConfig) if args.replay_config else ReplayConfig()
    replay_cfg.kind = args.replay
    if args.lam is not None:
        replay_cfg.lam = float(args.lam)
    if args.batch_size is not None:
        dqn_cfg.batch_size = int(args.batch_size)
    validate(dqn_cfg)
    validate(replay_cfg)
    return dqn_cfg, replay_cfg


def run_train(args: argparse.Namespace) -> int:
    if args.steps is not None and args.steps < 0:
        raise ConfigError(f"--steps = {args.steps}, expected >= 0")
    if args.eval_episodes < 0:
        raise ConfigError(f"--eval-episodes = {args.eval_episodes}, expected >= 0")
    dqn_cfg, replay_cfg = _configs(args)
    obs_cfg = None
    if args.obs_config is not None:
        obs_cfg = load_yaml(args.obs_config, ObservationConfig)
    parts = [build_transitions(BagReader(b), obs_cfg, args.namespace) for b in args.bags]
    total = sum(len(p) for p in parts)
    if total < dqn_cfg.batch_size:
        raise BagError(args.bags[0], None, f"only {total} transitions in the bags, fewer than the batch size "
                       f"{dqn_cfg.batch_size} (use --batch-size)")
    tr = concat_transitions(parts)
    replay_cfg.capacity = max(replay_cfg.capacity, len(tr))
    steps = args.steps if args.steps is not None else 2 * len(tr)
    res = train_offline(tr, dqn_cfg, replay_cfg, steps, seed=args.seed)
    if args.save is not None:
        res.agent.save(args.save)
    env_id, env_kwargs = args.env, {}
    scenario = recorded_scenario(args.bags[0]) if env_id is None else None
    if env_id is None:
        network = (scenario or {}).pop("network", "ring")
        env_id = NETWORK_ENV_IDS.get(network, DEFAULT_ENV)
        if scenario:
            env_kwargs = {"scenario": scenario}
            log.info("evaluating on the recorded scenario (%s, from params.yaml beside the bag)", env_id)
    if obs_cfg is not None and env_id.startswith("der_ros/"):
        env_kwargs.setdefault("scenario", {})["observation"] = asdict(obs_cfg)
    offline = (evaluate_policy(res.agent, env_id, args.eval_episodes, seed=args.seed,
                               max_episode_steps=args.max_episode_steps, env_kwargs=env_kwargs)
               if args.eval_episodes > 0 else None)
    online = online_numbers(list(args.bags), args.namespace)
    result = {
        "transitions": res.transitions,
        "gradient_steps": res.gradient_steps,
        "train_seconds": round(res.train_seconds, 3),
        "env": env_id,
        "replay": replay_cfg.kind,
        "lam": replay_cfg.lam,
        "final_metrics": res.final_metrics,
        "offline_eval": offline,
        "online_from_bags": online,
    }
    if args.json:
        print(json.dumps(result, default=float))
        return 0
    print(f"offline training: {res.transitions} transitions, {res.gradient_steps} gradient steps "
          f"({replay_cfg.kind}{f', lambda {replay_cfg.lam}' if replay_cfg.kind == 'der' else ''}) "
          f"in {res.train_seconds:.1f} s")
    for k, v in sorted(res.final_metrics.items()):
        print(f"  {k} = {v:.4g}")

    def fmt(x: Any, pct: bool = False) -> str:
        if x is None or (isinstance(x, float) and math.isnan(x)):
            return "-"
        return f"{x:.0%}" if pct else f"{x:.3f}"

    print(f"\n{'':24}{'episodes':>10}{'return':>10}{'success':>10}{'collision':>11}")
    for name, d in (("online agent (bags)", online), ("offline agent (greedy)", offline)):
        if d is None:
            continue
        print(f"{name:24}{d['episodes']:>10}{fmt(d['mean_return']):>10}{fmt(d['success_rate'], True):>10}"
              f"{fmt(d['collision_rate'], True):>11}")
    return 0
