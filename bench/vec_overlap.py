"""Benchmark: how N env workers overlap, with an environment that needs no CPU (not a test).

``bench/train_loop.py`` measures ``train.num_envs`` on the ring, where each worker needs a core: on a
shared machine with no free core, N = 2 cannot be faster than N = 1 whatever the loop does. This script
separates the loop's overlap from the core count: ``SleepEnv`` sleeps ``--ms`` per step (an env whose time
goes elsewhere: a simulator on other cores or machines), so N workers can only gain by stepping side by
side. Our loop (``der_ros.train.runner.train`` with ``train.num_envs`` N; N = 1 is the default env worker
loop) against SB3's DQN on a ``SubprocVecEnv`` of N (``gradient_steps=-1``: one gradient step per decision
collected, as ours), the same small MLP learner (CartPole-sized: obs 4, 64 hidden, batch 32).
Rates are decisions per second from learning start to the end of learning (SB3: ``learn()``; ours: the
last episode end), the speed-ups against N = 1 of the same loop; the ideal is N.

    .venv/bin/python bench/vec_overlap.py              # --ms 10, 1,500 decisions, N = 1, 2, 4
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

CARTPOLE_YAML = Path(__file__).resolve().parent.parent / "config" / "cartpole.yaml"


class SleepEnv(gym.Env):
    """Episodes of 20 steps; each step sleeps ``ms`` milliseconds and returns a random observation."""

    def __init__(self, ms: float = 10.0) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.ms, self.t = float(ms), 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self.np_random.uniform(-1, 1, 4).astype(np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        time.sleep(self.ms / 1000.0)
        self.t += 1
        return self.np_random.uniform(-1, 1, 4).astype(np.float32), 1.0, False, self.t >= 20, {}


if "SleepEnv-v0" not in gym.registry:  # imported twice in the main process: as __main__ and as vec_overlap
    gym.register("SleepEnv-v0", entry_point=SleepEnv)
ENV_ID = "vec_overlap:SleepEnv-v0"  # the module is imported by gymnasium in every worker process


def overrides(steps: int, ms: float, n: int) -> dict[str, Any]:
    return {
        "env.id": ENV_ID, "env.kwargs": {"ms": ms}, "agent.hidden_sizes": [64], "agent.batch_size": 32,
        "agent.learning_starts": 200, "replay.kind": "uniform", "replay.capacity": 10_000,
        "train.total_steps": steps, "train.num_envs": n, "train.env_process": True, "train.tensorboard": False,
        "train.progress": False, "train.save_final_checkpoint": False, "train.eval_interval": 0,
        "train.final_eval_episodes": 0, "train.device": "cpu",
    }  # fmt: skip


def ours(steps: int, ms: float, n: int) -> float:
    from der_ros.train.config import load_experiment_config
    from der_ros.train.runner import train

    cfg = load_experiment_config(CARTPOLE_YAML, overrides(steps, ms, n))
    marks: list[tuple[float, int]] = []
    with tempfile.TemporaryDirectory() as tmp:
        train(cfg, run_dir=tmp, on_episode=lambda e, s, r: marks.append((time.perf_counter(), s)))
    t1, s1 = next(m for m in marks if m[1] >= cfg.agent.learning_starts)
    t2, s2 = marks[-1]
    return (s2 - s1) / (t2 - t1)


def sb3(steps: int, ms: float, n: int) -> float:
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import SubprocVecEnv

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.start: tuple[float, int] | None = None

        def _on_step(self) -> bool:
            if self.start is None and self.num_timesteps >= 200:
                self.start = (time.perf_counter(), self.num_timesteps)
            return True

    env = SubprocVecEnv([functools.partial(gym.make, ENV_ID, ms=ms) for _ in range(n)])
    try:
        model = DQN("MlpPolicy", env, learning_starts=200, batch_size=32, buffer_size=10_000, train_freq=1,
                    gradient_steps=-1, policy_kwargs={"net_arch": [64]}, seed=0, device="cpu", verbose=0)  # fmt: skip
        clock = Clock()
        model.learn(total_timesteps=steps, callback=clock)
        t_end, done = time.perf_counter(), model.num_timesteps
    finally:
        env.close()
    assert clock.start is not None
    return (done - clock.start[1]) / (t_end - clock.start[0])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ms", type=float, default=10.0, help="milliseconds each env step sleeps")
    parser.add_argument("--steps", type=int, default=1500, help="decisions per run")
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 2, 4], help="numbers of env workers")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rates: dict[str, dict[int, float]] = {"ours": {}, "sb3": {}}
    for n in args.envs:
        rates["ours"][n] = ours(args.steps, args.ms, n)
        rates["sb3"][n] = sb3(args.steps, args.ms, n)
        print(f"N={n}: ours {rates['ours'][n]:.0f} decisions/s, SB3 SubprocVecEnv {rates['sb3'][n]:.0f}", file=sys.stderr)
    base = args.envs[0]
    print(json.dumps({
        "bench": "vec_overlap", "env_step_ms": args.ms, "steps": args.steps, "ideal_per_s": round(1000.0 / args.ms, 1),
        **{f"ours_n{n}_per_s": round(r, 1) for n, r in rates["ours"].items()},
        **{f"sb3_n{n}_per_s": round(r, 1) for n, r in rates["sb3"].items()},
        **{f"vec_speedup_n{n}": round(rates["ours"][n] / rates["ours"][base], 3) for n in args.envs[1:]},
        **{f"sb3_vec_speedup_n{n}": round(rates["sb3"][n] / rates["sb3"][base], 3) for n in args.envs[1:]},
    }))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
