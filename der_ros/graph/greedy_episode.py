"""The GIF at the end of ``der graph``: one greedy episode of the trained agent, to watch.

The graph's own bag holds training episodes (epsilon-greedy actions of a learner that was still
changing), so the episode shown is a fresh one: the final checkpoint's Q-network acting greedily
(epsilon = 0) on the first evaluation seed (``EVAL_SEED_BASE``, held out from training), in a plain
LaneChangeEnv of the bridge's scenario -- the first episode of the final evaluation, the same
decisions and return (with ``commit_on_success`` switched off, so the film goes on to the horizon
instead of stopping at the lane change). It runs in a spawned process (one libsumo simulation per
process, and torch stays out of ``der graph``'s own process), which records the episode as the graph would
(:func:`der_ros.offline.episode_recording.record_episode`: ``<run dir>/greedy_episode/``, a small bag)
and renders it with ``der bag render``'s renderer to ``<run dir>/plots/greedy_episode.gif``.
A failure here is logged and the run's summary goes on without the GIF.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.agent.config import DQNConfig
from der_ros.graph.snapshot_evaluation import observation_shape, scenario_env_config
from der_ros.offline.episode_recording import record_episode
from der_ros.offline.render import render_bag
from der_ros.safety.checker import RssChecker
from der_ros.safety.config import SafetyConfig
from der_ros.train.config import EnvConfig
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_policies import GreedyQPolicy
from der_ros.train.eval_seeds import EVAL_SEED_BASE

__all__ = ["GreedyEpisode", "GIF_NAME", "BAG_NAME", "greedy_episode_gif", "watchable_env_config"]

log = logging.getLogger("der.graph")

GIF_NAME = "greedy_episode.gif"
BAG_NAME = "greedy_episode"


@dataclass(frozen=True)
class GreedyEpisode:
    """The rendered episode: where it is and how it went."""

    gif: Path
    bag: Path
    seed: int
    steps: int
    ret: float
    outcome: str

    def describe(self) -> str:
        return f"greedy, held-out seed {self.seed}: {self.outcome}, return {self.ret:+.2f} in {self.steps} steps"


def _record_and_render(checkpoint: str, env_cfg: EnvConfig, network: str, hidden: list[int], n_actions: int,
                       seed: int, bag: str, gif: str, shield: SafetyConfig | None = None) -> dict[str, Any]:  # fmt: skip
    """In the spawned process: load the Q-network, run the episode into ``bag``, render ``gif``."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from der_ros.agent.dqn import read_checkpoint
    from der_ros.agent.networks import make_q_network

    torch.set_num_threads(1)
    state = read_checkpoint(checkpoint)["agent"]
    net = make_q_network(observation_shape(env_cfg), np.float32, n_actions, network, hidden)
    net.load_state_dict(state["q_net"])
    net.eval()
    policy = GreedyQPolicy(net, np.dtype(np.float32))
    env = make_env_from_config(env_cfg, seed)
    try:
        mask = RssChecker(shield).mask if shield is not None and shield.kind == "rss" else None  # as the safety node
        rec = record_episode(env.unwrapped, lambda obs: int(policy(obs[None], [{}])[0]), bag, seed=seed, shield=mask)
    finally:
        env.close()
    render_bag(bag, gif)
    return {"steps": rec.steps, "ret": rec.ret, "outcome": rec.outcome}


def watchable_env_config(env_cfg: EnvConfig) -> EnvConfig:
    """``env_cfg`` with ``commit_on_success`` off: a commit ends the episode in the step of the lane
    change, which would cut the film there; the plain horizon shows the ego driving on to the end,
    with the same decisions and the same return."""
    scenario = dict(env_cfg.kwargs.get("scenario") or {})
    if not scenario.get("commit_on_success"):
        return env_cfg
    scenario["commit_on_success"] = False
    return replace(env_cfg, kwargs={**env_cfg.kwargs, "scenario": scenario})


def greedy_episode_gif(run_dir: Path, checkpoint: Path, params: dict[str, Any],
                       timeout: float = 900.0, shield: SafetyConfig | None = None) -> GreedyEpisode | None:  # fmt: skip
    """Record and render the greedy episode of ``checkpoint`` (a ``der graph`` run's ``agent.pt``)
    with the run's ``params``; None (and a warning) if anything fails. ``shield``: the episode runs
    behind it as behind the graph's safety node (vetoed steps marked in the film)."""
    bridge = params["bridge_node"]["ros__parameters"]
    agent = params["agent_node"]["ros__parameters"]
    defaults = DQNConfig()
    gif = Path(run_dir) / "plots" / GIF_NAME
    bag = Path(run_dir) / BAG_NAME
    try:
        gif.parent.mkdir(parents=True, exist_ok=True)
        with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
            job = pool.submit(
                _record_and_render, str(checkpoint), watchable_env_config(scenario_env_config(bridge)),
                str(agent.get("agent.network", defaults.network)),
                [int(h) for h in agent.get("agent.hidden_sizes", defaults.hidden_sizes)],
                int(agent.get("n_actions", 3)), EVAL_SEED_BASE, str(bag), str(gif), shield,
            )  # fmt: skip
            out = job.result(timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - the GIF must not turn a finished run into a failure
        log.warning("greedy episode GIF failed: %s: %s", type(exc).__name__, exc)
        return None
    return GreedyEpisode(gif, bag, EVAL_SEED_BASE, int(out["steps"]), float(out["ret"]), str(out["outcome"]))
