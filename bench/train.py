"""Benchmark: CartPole training throughput, der_ros DQN vs Stable-Baselines3 DQN (not a test).

Same work for both: CartPole-v1, MLP with one hidden layer of 256, batch 128, Adam lr 5e-4,
gamma 0.98, Huber loss (SB3's), gradient-norm clip 10, one gradient step per environment step,
the same learning_starts, target update every 200 steps, epsilon 1 -> 0.02 over 2,000 steps,
buffer 50,000, torch with one thread, CPU. Measured: environment steps per second of the whole
training call (ours: ``der_ros.train.runner.train`` with CSV metrics on, TensorBoard and the
progress bar off; SB3: ``DQN.learn``), both by wall clock and by process CPU time (the CPU
figure is steadier on a shared machine). After a short warm-up of each, every side runs
``--repeats`` times, interleaved; the best run counts (least disturbed by other load). Ends with
one JSON line.

    .venv/bin/python bench/train.py            # 10,000 steps (the paper's CartPole length)
    .venv/bin/python bench/train.py --quick    # 2,000 steps, a few seconds
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

torch.set_num_threads(1)

from der_ros.train.config import load_experiment_config  # noqa: E402
from der_ros.train.runner import train  # noqa: E402

LEARNING_STARTS = 500
TARGET_UPDATE = 200
EPS_DECAY = 2000


def ours(steps: int, kind: str, lam: float = 0.9) -> tuple[float, float]:
    """(wall, CPU) steps/s of our runner with replay ``kind``."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_experiment_config(
            None,
            {
                "env.id": "CartPole-v1",
                "agent.lr": 5e-4,
                "agent.gamma": 0.98,
                "agent.batch_size": 128,
                "agent.network": "mlp",
                "agent.hidden_sizes": [256],
                "agent.loss": "huber",
                "agent.max_grad_norm": 10.0,
                "agent.target_update_interval": TARGET_UPDATE,
                "agent.tau": 1.0,
                "agent.learning_starts": LEARNING_STARTS,
                "agent.train_freq": 1,
                "agent.gradient_steps": 1,
                "agent.epsilon_start": 1.0,
                "agent.epsilon_end": 0.02,
                "agent.epsilon_decay_steps": EPS_DECAY,
                "replay.kind": kind,
                "replay.capacity": 50_000,
                "replay.lam": lam,
                "train.total_steps": steps,
                "train.seed": 0,
                "train.device": "cpu",
                "train.threads": 1,
                "train.tensorboard": False,
                "train.progress": False,
                "train.save_final_checkpoint": False,
                "train.log_interval": 100,
            },
        )
        t0, c0 = time.perf_counter(), time.process_time()
        summary = train(cfg, run_dir=tmp)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        assert summary.steps == steps
    return steps / dt, steps / dc


def sb3(steps: int) -> tuple[float, float]:
    """(wall, CPU) steps/s of Stable-Baselines3 DQN with the same settings."""
    import gymnasium as gym
    from stable_baselines3 import DQN

    env = gym.make("CartPole-v1")
    model = DQN(
        "MlpPolicy",
        env,
        learning_rate=5e-4,
        buffer_size=50_000,
        learning_starts=LEARNING_STARTS,
        batch_size=128,
        tau=1.0,
        gamma=0.98,
        train_freq=1,
        gradient_steps=1,
        target_update_interval=TARGET_UPDATE,
        exploration_fraction=EPS_DECAY / steps,
        exploration_initial_eps=1.0,
        exploration_final_eps=0.02,
        max_grad_norm=10.0,
        policy_kwargs={"net_arch": [256]},
        seed=0,
        device="cpu",
        verbose=0,
    )
    t0, c0 = time.perf_counter(), time.process_time()
    model.learn(total_timesteps=steps)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    env.close()
    return steps / dt, steps / dc


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2,000 steps, 1 repeat")
    parser.add_argument("--steps", type=int, default=None, help="environment steps per run (default 10,000)")
    parser.add_argument("--repeats", type=int, default=None, help="runs per side (default 2, 1 with --quick)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    steps = args.steps or (2_000 if args.quick else 10_000)
    repeats = args.repeats or (1 if args.quick else 2)

    names = ("ours", "sb3", "ours_der", "ours_per")
    wall: dict[str, float] = dict.fromkeys(names, 0.0)
    cpu: dict[str, float] = dict.fromkeys(names, 0.0)
    sb3(min(steps, 1_000))  # warm-up: first-call costs (imports, allocator) hit neither side
    ours(min(steps, 1_000), "uniform")
    for r in range(repeats):
        for name, fn in (
            ("ours", lambda: ours(steps, "uniform")),
            ("sb3", lambda: sb3(steps)),
            ("ours_der", lambda: ours(steps, "der", 0.9)),
            ("ours_per", lambda: ours(steps, "per")),
        ):
            w, c = fn()
            wall[name] = max(wall[name], w)
            cpu[name] = max(cpu[name], c)
            print(
                f"repeat {r + 1}/{repeats} {name:9s} {w:8.0f} steps/s wall {c:8.0f} steps/CPU-s",
                file=sys.stderr,
                flush=True,
            )

    result = {
        "bench": "train",
        "env": "CartPole-v1",
        "steps": steps,
        "repeats": repeats,
        "ours_steps_per_s": round(wall["ours"], 1),
        "sb3_steps_per_s": round(wall["sb3"], 1),
        "ours_der_steps_per_s": round(wall["ours_der"], 1),
        "ours_per_steps_per_s": round(wall["ours_per"], 1),
        "ratio_ours_vs_sb3": round(wall["ours"] / wall["sb3"], 3),
        "ratio_ours_der_vs_sb3": round(wall["ours_der"] / wall["sb3"], 3),
        "ratio_ours_per_vs_sb3": round(wall["ours_per"] / wall["sb3"], 3),
        "ours_steps_per_cpu_s": round(cpu["ours"], 1),
        "sb3_steps_per_cpu_s": round(cpu["sb3"], 1),
        "ours_der_steps_per_cpu_s": round(cpu["ours_der"], 1),
        "ratio_ours_vs_sb3_cpu": round(cpu["ours"] / cpu["sb3"], 3),
        "ratio_ours_der_vs_sb3_cpu": round(cpu["ours_der"] / cpu["sb3"], 3),
        "torch_threads": torch.get_num_threads(),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
