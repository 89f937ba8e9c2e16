"""Greedy evaluations of the policy a ``der graph`` run is training (ROS-free).

The agent node writes a small policy snapshot (:func:`der_ros.train.eval_policies.save_policy`)
at start and every ``policy_every`` steps; this module evaluates each one greedily (epsilon = 0)
on held-out evaluation seeds in a second process with its own SUMO simulation of the bridge's
scenario (:class:`der_ros.train.evaluation.ProcessEvaluator`), so the graph keeps training while
it runs. At the end the agent's final checkpoint is evaluated on more episodes: the numbers
``der graph`` (and ``./scripts/run.sh``) ends its summary with. Results go to the run directory
as ``evaluations.csv`` and ``evaluation.json``, the same files ``der train`` writes.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from der_ros.agent.config import DQNConfig
from der_ros.configuration import from_dict
from der_ros.safety.config import SafetyConfig
from der_ros.train.config import EnvConfig
from der_ros.train.eval_policies import load_policy, policy_files
from der_ros.train.eval_result import EVALUATIONS_CSV, FINAL_EVAL_JSON, EvalResult, write_eval_row
from der_ros.train.eval_seeds import EVAL_SEED_BASE, check_disjoint, evaluation_seeds
from der_ros.train.evaluation import make_evaluator
from sumo_bridge import NETWORK_ENV_IDS, SCENARIO_ENV_ID
from sumo_bridge.observation import ObservationConfig, observation_size

__all__ = ["GraphEvaluator", "observation_shape", "scenario_env_config"]

log = logging.getLogger("der.graph")

#: episodes per seeded reset (urban keeps its traffic running; a seeded reset warms up 150 s)
_EPISODES_PER_SEED = {"ring": 1, "urban": 10}


def _nested(flat: dict[str, Any], prefix: str) -> dict[str, Any]:
    """``{"scenario.a": 1, "scenario.observation.b": 2}`` -> ``{"a": 1, "observation": {"b": 2}}``."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        if not key.startswith(prefix + "."):
            continue
        parts = key[len(prefix) + 1 :].split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def scenario_env_config(bridge_params: dict[str, Any]) -> EnvConfig:
    """The gymnasium env of the bridge's scenario (its ``scenario.*`` parameters)."""
    scenario = _nested(bridge_params, "scenario")
    network = str(scenario.get("network", "ring"))
    scenario.pop("network", None)
    scenario.pop("gui", None)  # evaluations run headless
    if network not in NETWORK_ENV_IDS:  # a scenario file (scenario.file); its other fields as overrides
        return EnvConfig(id=SCENARIO_ENV_ID, kwargs={"scenario": scenario})
    return EnvConfig(id=NETWORK_ENV_IDS[network], kwargs={"scenario": scenario})


def graph_safety_config(params: dict[str, Any]) -> SafetyConfig:
    """The safety node's shield (its ``safety.*`` parameters), in replace mode as the node applies it."""
    shield = _nested(params["safety_node"]["ros__parameters"], "safety")
    return from_dict(SafetyConfig, {**shield, "mode": "replace"}, source="safety_node")


def observation_shape(env_cfg: EnvConfig) -> tuple[int]:
    """The observation shape of a lane-change env config (its ``scenario.observation`` fields decide
    whether the required-deceleration block is in)."""
    scenario = env_cfg.kwargs.get("scenario") or {}
    obs_cfg = from_dict(ObservationConfig, scenario.get("observation"), source="scenario.observation")
    return (observation_size(obs_cfg),)


class GraphEvaluator:
    """Evaluates a running graph's policy snapshots and, at the end, its final checkpoint."""

    def __init__(self, run_dir: Path, params: dict[str, Any], policy_dir: Path, episodes: int,
                 final_episodes: int, shielded: bool = False) -> None:  # fmt: skip
        bridge = params["bridge_node"]["ros__parameters"]
        agent = params["agent_node"]["ros__parameters"]
        self.env_cfg = scenario_env_config(bridge)
        if shielded:  # evaluated behind the same shield as the graph's safety node (replace mode)
            self.env_cfg.safety = graph_safety_config(params)
        network = str(bridge.get("scenario.network", "ring"))
        self.per_seed = _EPISODES_PER_SEED.get(network, 1)
        self.episodes, self.final_episodes = int(episodes), int(final_episodes)
        most = max(self.episodes, self.final_episodes)
        check_disjoint([int(bridge.get("scenario.seed", 0))],
                       evaluation_seeds(-(-most // self.per_seed), EVAL_SEED_BASE))  # fmt: skip
        defaults = DQNConfig()
        self.run_dir, self.policy_dir = Path(run_dir), Path(policy_dir)
        self.csv = self.run_dir / EVALUATIONS_CSV
        self._evaluator = make_evaluator(
            self.env_cfg, observation_shape(self.env_cfg), "float32", int(agent.get("n_actions", 3)),
            str(agent.get("agent.network", defaults.network)), list(agent.get("agent.hidden_sizes", defaults.hidden_sizes)),
            self.per_seed, EVAL_SEED_BASE, mode="process",
        )  # fmt: skip
        self._submitted: set[Path] = set()
        self.last: EvalResult | None = None
        self.final: EvalResult | None = None

    def poll(self) -> EvalResult | None:
        """Submit new snapshots, record finished evaluations; the latest result (or None)."""
        if self.episodes:
            for path in policy_files(self.policy_dir):
                if path not in self._submitted:
                    self._submitted.add(path)
                    steps, state = load_policy(path)
                    self._evaluator.submit(steps, state, self.episodes)
        self._record(self._evaluator.poll())
        return self.last

    def _record(self, results: list[EvalResult]) -> None:
        for res in sorted(results, key=lambda r: r.step):
            write_eval_row(self.csv, res)
            self.last = res

    def finish(self, checkpoint: Path | None) -> EvalResult | None:
        """Wait for the pending evaluations, then evaluate the final checkpoint (``final_episodes``)."""
        self.poll()
        if checkpoint is not None and checkpoint.is_file() and self.final_episodes:
            from der_ros.agent.dqn import read_checkpoint  # lazy: torch

            state = read_checkpoint(checkpoint)["agent"]
            weights = {k: v.cpu().numpy() for k, v in state["q_net"].items()}
            self._evaluator.submit(int(state["steps"]), weights, self.final_episodes)
            results = self._evaluator.finish()
            self._record(results)
            finals = [r for r in results if r.n == self.final_episodes and r.step == int(state["steps"])]
            if finals:
                self.final = finals[-1]
                self.final.save(self.run_dir / FINAL_EVAL_JSON)
        else:
            self._record(self._evaluator.finish())
        return self.final

    def close(self) -> None:
        self._evaluator.close()
