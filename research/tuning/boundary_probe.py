"""How well trained nets know the ring's safe-gap boundary: lane changes with known outcomes, scored per net.

A greedy evaluation of 1,800 episodes meets a lane change at the edge of the safe gap a few times;
comparing two settings on a handful of caused collisions is close to noise. This probe asks every
net about the same few thousand lane-change states instead:

``collect`` drives ring episodes from the diagnostic seed stream (``--seed``, default
2,000,000,000: disjoint from training seeds, the report evaluation seeds ``1e9 + k`` and the tuning
evaluation seeds ``1.5e9 + k``; one seeded reset, then the env's own stream). In each episode the
ego keeps its lane for k ~ U{0, ..., 11} decisions, then commands a change towards the target lane
once; the points before the change and whether the change caused a collision are saved (``.npz``).
Each state is simulated once, so near the boundary a label is one draw of a chance outcome.

``score`` loads each run's ``checkpoint.pt`` and ``config.yaml``, encodes the saved points with
that run's observation settings, and counts the states where the greedy action is the change:
those labelled *collided* (changes the net would take into a collision) and those labelled safe
(opportunities it takes). research/tuning/ring_dqn.md, tenth session.

    python research/tuning/boundary_probe.py collect config/ring.yaml --changes 6000 --out runs/boundary.npz
    python research/tuning/boundary_probe.py score runs/boundary.npz RUN_DIR [RUN_DIR ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import sumo_bridge  # noqa: F401 - registers the lane-change environments
from der_ros.configuration import from_dict
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from sumo_bridge import ENV_NETWORKS
from sumo_bridge.observation import ObservationConfig, encode_observation, field_index

DIAGNOSTIC_SEED = 2_000_000_000
MAX_WAIT = 11  #: decisions kept before the change: k ~ U{0, ..., MAX_WAIT}
_LANE, _TARGET = field_index("lane"), field_index("target_lane")


def _towards_target(ego_rows: np.ndarray) -> np.ndarray:
    """The action that changes towards the target lane: 1 (left) where it is above the ego's lane, else 2."""
    return np.where(ego_rows[..., _TARGET] > ego_rows[..., _LANE], 1, 2)


def collect(config: Path, changes: int, seed: int, out: Path) -> None:
    cfg = load_experiment_config(config)
    if ENV_NETWORKS.get(cfg.env.id) is None:
        raise SystemExit(f"{config}: env.id = {cfg.env.id!r} is not a SUMO lane-change env")
    env = make_env_from_config(cfg.env, seed)
    rng = np.random.default_rng(seed)
    points, collided = [], []
    try:
        _, info = env.reset(seed=seed)
        for episode in range(changes):
            if episode:
                _, info = env.reset()
            done = False
            for _ in range(int(rng.integers(0, MAX_WAIT + 1))):
                _, _, terminated, truncated, info = env.step(0)
                if terminated or truncated:
                    done = True
                    break
            if done:
                continue
            before = info["points"].copy()
            _, _, _, _, info = env.step(int(_towards_target(before[0])))
            points.append(before)
            collided.append(info["event"] == "collision" and bool(info["caused"]))
    finally:
        env.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, points=np.array(points), collided=np.array(collided, dtype=bool))
    print(f"{out}: {len(collided)} lane changes, {int(np.sum(collided))} caused a collision")


def score(data: Path, runs: list[Path]) -> None:
    import torch

    from der_ros.agent.dqn import DQNAgent

    d = np.load(data)
    points, collided = d["points"], d["collided"]
    total_bad = total_safe = 0
    for run in runs:
        cfg = load_experiment_config(run / "config.yaml")
        obs_cfg = from_dict(ObservationConfig, (cfg.env.kwargs.get("scenario") or {}).get("observation"),
                            source=f"{run}/config.yaml scenario.observation")  # fmt: skip
        x = np.stack([encode_observation(p, obs_cfg) for p in points]).astype(np.float32)
        net = DQNAgent.load(run / "checkpoint.pt").q_net.eval()
        with torch.no_grad():
            greedy = net(torch.as_tensor(x)).numpy().argmax(axis=1)
        takes = greedy == _towards_target(points[:, 0])
        bad, safe = int(np.sum(takes & collided)), int(np.sum(takes & ~collided))
        total_bad, total_safe = total_bad + bad, total_safe + safe
        print(f"{run}: takes {bad} of {int(collided.sum())} colliding changes, {safe} of {int((~collided).sum())} safe ones")
    print(f"total over {len(runs)} runs: {total_bad} colliding changes taken, {total_safe} safe ones")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="simulate lane changes with known outcomes")
    c.add_argument("config", type=Path)
    c.add_argument("--changes", type=int, default=6000, help="episodes to try (each ends in one change, unless its horizon ends first)")
    c.add_argument("--seed", type=int, default=DIAGNOSTIC_SEED)
    c.add_argument("--out", type=Path, required=True)
    s = sub.add_parser("score", help="count the changes each run's greedy net would take")
    s.add_argument("data", type=Path)
    s.add_argument("runs", nargs="+", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "collect":
        collect(args.config, args.changes, args.seed, args.out)
    else:
        score(args.data, args.runs)


if __name__ == "__main__":
    main()
