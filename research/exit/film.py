"""A greedy episode of a trained exit agent as a GIF (and a still), behind its own RSS shield.

    python research/exit/film.py RUN_DIR OUT.gif [--seed-offset K] [--still OUT.png]

RUN_DIR holds config.yaml and checkpoint.pt (``der train --config config/exit.yaml ...``); the
episode starts from the report evaluation seed EVAL_SEED_BASE + K (held out from training). The
episode is recorded as the graph would (a small bag beside the GIF) and drawn by ``der bag render``'s
renderer following the ego.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.agent.dqn import DQNAgent
from der_ros.graph.greedy_episode import watchable_env_config
from der_ros.offline.episode_recording import record_episode
from der_ros.offline.render import RenderOptions, render_bag
from der_ros.safety.apply import masked_argmax, with_speed_actions
from der_ros.safety.checker import RssChecker
from der_ros.safety.config import SafetyConfig
from der_ros.safety.wrapper import scenario_shield, target_mask_for
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_seeds import EVAL_SEED_BASE


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("out", type=Path, help="the GIF")
    parser.add_argument("--seed-offset", type=int, default=0, help="episode seed EVAL_SEED_BASE + K (default 0)")
    parser.add_argument("--still", type=Path, help="also save the frame where the ego is on the exit lane")
    parser.add_argument("--no-shield", action="store_true", help="the agent's commands go through unfiltered")
    args = parser.parse_args()
    cfg = load_experiment_config(args.run_dir / "config.yaml")
    agent = DQNAgent.load(args.run_dir / "checkpoint.pt")
    agent.q_net.eval()
    policy = GreedyQPolicy(agent.q_net, np.float32)
    seed = EVAL_SEED_BASE + args.seed_offset
    env = make_env_from_config(watchable_env_config(cfg.env), seed)
    # the run's own shield (as trained and evaluated: its parameters made at least as cautious as the
    # scenario's fleet, mask or replace); a run trained without one: the default RSS shield, replace
    run_shield = cfg.env.safety if cfg.env.safety.enabled else SafetyConfig(kind="rss")
    shield_cfg = scenario_shield(run_shield, getattr(env.unwrapped, "config", None))
    n_actions = int(env.action_space.n)
    check = RssChecker(shield_cfg)
    shield = None if args.no_shield else (lambda points: with_speed_actions(check.mask(points), n_actions))
    obs_mask = target_mask_for(cfg.env) if shield is not None else None  # mask mode: the same verdict from obs

    def act(obs: np.ndarray) -> int:
        if obs_mask is not None:  # the best allowed action, as the table's evaluation chooses it
            return masked_argmax(agent.q_values(obs), obs_mask(np.asarray(obs)[None])[0])
        return int(policy(obs[None], [{}])[0])

    bag = args.out.with_suffix(".bag")
    try:
        rec = record_episode(env.unwrapped, act, bag, seed=seed, shield=shield)
    finally:
        env.close()
    res = render_bag(bag, args.out, opts=RenderOptions(width=640, height=320, caption_height=64, follow_window=160.0))
    print(f"seed {seed}: {rec.outcome}, return {rec.ret:+.2f} in {rec.steps} steps; {res.frames} frames -> {args.out}")
    if args.still is not None:
        with Image.open(args.out) as gif:
            gif.seek(max(0, int(gif.n_frames * 0.6)))
            gif.convert("RGB").save(args.still)


if __name__ == "__main__":
    main()
