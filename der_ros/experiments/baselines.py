"""Baselines beside every learned result: trivial and scripted policies, and SUMO's own driver.

A learned policy that does not beat "never change lane" means the task or the objective is
broken, not that the method is weak; one that does not beat a simple gap-acceptance rule or
SUMO's own lane-change model is not worth deploying. So every table evaluates, on the very same
evaluation seeds as the learned agents (:mod:`der_ros.train.eval_seeds`):

SUMO lane change (``der_ros/LaneChange*``):

* ``keep`` -- never change lane;
* ``immediate`` -- change towards the target lane at every step, whatever the traffic;
* ``random`` -- uniformly random actions (seeded);
* ``gap_acceptance`` -- change only into a gap that is big enough
  (:func:`sumo_bridge.policies.gap_acceptance_policy`), with thresholds tuned on the *tuning*
  evaluation seeds (:func:`tune_gap_acceptance`, ``der baselines --tune``) and frozen in
  ``config/baselines.yaml``;
* ``sumo`` -- SUMO's own lane-change model given a standing request to reach the target lane:
  the immediate policy's command every step, with the ego's ``laneChangeMode`` at SUMO's default
  1621, so SUMO carries a change out only when its own safety checks allow it. In a scenario whose
  goal is an edge of the ego's route (an exit) nothing is commanded: SUMO's strategic lane changes
  take the ego there.

Scenarios with an exit (a goal edge) add two rules a user expects there (:data:`EXIT_BASELINES`):

* ``mobil`` -- IDM+MOBIL as the ego's driver: SUMO's IDM car-following (the scenario's vType
  :data:`MOBIL_EGO_TYPE`) and MOBIL with a mandatory-exit bias choosing keep / left / right
  (:mod:`sumo_bridge.mobil`; never the speed actions); the bias (and b_safe) tuned on the tuning seeds
  and frozen in ``config/baselines.yaml`` (:mod:`der_ros.experiments.rule_params`);
* ``sumo_tuned`` -- ``sumo`` with the ego's LC2013 lane-change parameters (``lcAssertive``, ...)
  tuned on the tuning seeds and frozen there: the default row alone would be a strawman.

CartPole: ``random``, ``constant`` (always push left) and ``scripted`` (push towards where the
pole falls: the sign of angle + 0.5 x angular velocity).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import itertools
import json
import logging
import math
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from der_ros.configuration import ConfigError, read_yaml_mapping, to_dict, validate
from der_ros.experiments.rule_params import lane_change_entries, load_mobil_params, load_sumo_tuned_params
from der_ros.experiments.table_report import write_markdown
from der_ros.safety.config import SAFETY_KINDS, SAFETY_MODES, SafetyConfig
from der_ros.safety.wrapper import shield_in_force
from der_ros.train.config import EnvConfig, load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_policies import Policy
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE, evaluation_seeds
from sumo_bridge import ENV_NETWORKS
from sumo_bridge.mobil import MobilParams, mobil_policy
from sumo_bridge.policies import gap_acceptance_policy, immediate_policy, keep_policy
from sumo_bridge.scenario_file import load_scenario, scenario_from_kwargs

__all__ = [
    "SUMO_BASELINES",
    "EXIT_BASELINES",
    "MOBIL_EGO_TYPE",
    "rule_params",
    "baseline_job",
    "CARTPOLE_BASELINES",
    "GapAcceptanceParams",
    "baseline_names",
    "load_gap_params",
    "baseline_policy",
    "baseline_env_config",
    "shielded_env_config",
    "SHIELDED_BASELINES",
    "evaluate_baseline",
    "run_baselines",
    "tune_gap_acceptance",
    "pick_gap",
    "add_arguments",
    "run",
]

log = logging.getLogger(__name__)

SUMO_BASELINES = ("keep", "immediate", "random", "gap_acceptance", "sumo")
#: the baselines of scenarios whose goal is an exit (an edge of the ego's route)
EXIT_BASELINES = ("keep", "immediate", "random", "gap_acceptance", "mobil", "sumo", "sumo_tuned")
#: the vType the ``mobil`` baseline's ego drives with: SUMO's IDM with sumo_bridge.idm.IdmParams' values
#: (defined in the exit scenario's demand, sumo_bridge/scenarios/exit/exit.rou.xml)
MOBIL_EGO_TYPE = "ego_idm"
CARTPOLE_BASELINES = ("random", "constant", "scripted")
#: SUMO's default laneChangeMode: its own model, commanded changes only when safe (bits 8-9 = 10)
SUMO_DEFAULT_LANE_CHANGE_MODE = 1621
DEFAULT_PARAMS_FILE = Path(__file__).resolve().parents[2] / "config" / "baselines.yaml"


@dataclass(frozen=True)
class GapAcceptanceParams:
    """Thresholds of :func:`sumo_bridge.policies.gap_acceptance_policy` (metres, seconds)."""

    lead_gap: float = 2.0
    follow_gap: float = 3.0
    time_headway: float = 1.0


def _network(env_cfg: EnvConfig) -> str | None:
    """'ring' / 'urban' / a scenario file's name for the SUMO ids, None otherwise."""
    network = ENV_NETWORKS.get(env_cfg.id)
    if network == "scenario":
        return scenario_from_kwargs("scenario", (env_cfg.kwargs or {}).get("scenario")).network
    return network


def _goal_by_route(env_cfg: EnvConfig) -> bool:
    """True for a scenario whose goal is an edge of the ego's route (an exit): SUMO's own model gets
    there by its strategic lane changes, so the ``sumo`` baseline commands nothing (keep)."""
    if ENV_NETWORKS.get(env_cfg.id) != "scenario":
        return False
    cfg = scenario_from_kwargs("scenario", (env_cfg.kwargs or {}).get("scenario"))
    return bool(cfg.file) and load_scenario(cfg.file).goal.edge is not None


def baseline_names(env_cfg: EnvConfig) -> tuple[str, ...]:
    """The baselines of this environment (none for Atari)."""
    if _network(env_cfg) is not None:
        return EXIT_BASELINES if _goal_by_route(env_cfg) else SUMO_BASELINES
    if env_cfg.id.startswith("CartPole"):
        return CARTPOLE_BASELINES
    return ()


def load_gap_params(network: str, path: str | Path = DEFAULT_PARAMS_FILE) -> GapAcceptanceParams:
    """The tuned gap-acceptance thresholds of ``network`` from ``config/baselines.yaml``."""
    data = read_yaml_mapping(Path(path), expected="a mapping of baselines")
    section = (data.get("gap_acceptance") or {}).get(network)
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: gap_acceptance.{network} missing, expected lead_gap/follow_gap/time_headway")
    section = {k: v for k, v in section.items() if k != "tuned"}  # see gap_params_tuned
    unknown = set(section) - {"lead_gap", "follow_gap", "time_headway"}
    if unknown:
        raise ConfigError(f"{path}: gap_acceptance.{network}: unknown keys {sorted(unknown)}")
    try:
        params = GapAcceptanceParams(**{k: float(v) for k, v in section.items()})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: gap_acceptance.{network} = {section!r}: {exc}") from None
    for k, v in params.__dict__.items():
        if not math.isfinite(v) or v < 0:
            raise ConfigError(f"{path}: gap_acceptance.{network}.{k} = {v!r}, expected a finite value >= 0")
    return params


def gap_params_tuned(network: str, path: str | Path = DEFAULT_PARAMS_FILE) -> bool:
    """Whether ``config/baselines.yaml`` marks ``network``'s thresholds as tuned (``tuned: false`` = a
    hand-set starting point; absent = tuned)."""
    data = read_yaml_mapping(Path(path), expected="a mapping of baselines")
    tuned = ((data.get("gap_acceptance") or {}).get(network) or {}).get("tuned", True)
    if not isinstance(tuned, bool):
        raise ConfigError(f"{path}: gap_acceptance.{network}.tuned = {tuned!r}, expected true or false")
    return tuned


def rule_params(name: str, network: str, path: str | Path = DEFAULT_PARAMS_FILE) -> Any:
    """The frozen parameters baseline ``name`` runs with on ``network`` (None for a rule without any):
    :class:`GapAcceptanceParams`, :class:`~sumo_bridge.mobil.MobilParams` or the ``sumo_tuned`` ego's
    lane-change parameters (a dict)."""
    name = name.removesuffix(_SHIELD)
    if name == "gap_acceptance":
        return load_gap_params(network, path)
    if name == "mobil":
        return load_mobil_params(network, path)
    if name == "sumo_tuned":
        return load_sumo_tuned_params(network, path)
    return None


def _per_env(rule: Any) -> Policy:
    return lambda obs, infos: [int(rule(info["points"])) for info in infos]


def baseline_policy(name: str, gap: GapAcceptanceParams | None = None, seed: int = 0,
                    mobil: MobilParams | None = None, n_actions: int | None = None) -> Policy:
    """The batched policy of baseline ``name`` (points-based for SUMO, observation-based for CartPole);
    ``n_actions``: the env's action count, which ``random`` draws from (default 3 for SUMO, 2 for CartPole)."""
    if name == "keep":
        return _per_env(keep_policy)
    if name in ("immediate", "sumo", "sumo_tuned"):
        return _per_env(immediate_policy)
    if name == "mobil":
        m = mobil or MobilParams()
        return _per_env(lambda p: mobil_policy(p, m))
    if name == "gap_acceptance":
        g = gap or GapAcceptanceParams()
        return _per_env(lambda p: gap_acceptance_policy(p, g.lead_gap, g.follow_gap, g.time_headway))
    if name == "random":
        rng = np.random.default_rng(seed)
        return lambda obs, infos: [int(a) for a in rng.integers(0, n_actions or (3 if "points" in infos[0] else 2), size=len(obs))]
    if name == "constant":
        return lambda obs, infos: [0] * len(obs)
    if name == "scripted":
        return lambda obs, infos: [int(o[2] + 0.5 * o[3] > 0) for o in obs]
    raise ValueError(f"baseline {name!r} unknown; expected one of {', '.join(EXIT_BASELINES + CARTPOLE_BASELINES)}")


#: the baselines ``der table3 --shield`` / ``der baselines --safety`` also run behind the shield (as ``<name>+shield``)
SHIELDED_BASELINES = ("immediate", "random", "gap_acceptance")
_SHIELD = "+shield"


def shielded_env_config(env_cfg: EnvConfig, kind: str, mode: str | None = None) -> EnvConfig:
    """A copy of ``env_cfg`` with the safety shield ``kind`` (and ``mode``) on."""
    out = copy.deepcopy(env_cfg)
    out.safety = dataclasses.replace(out.safety, kind=kind, **({"mode": mode} if mode else {}))
    return validate(out, source="safety")


def baseline_env_config(env_cfg: EnvConfig, name: str, params: Any = None) -> EnvConfig:
    """The env config a baseline runs on (``sumo``: the ego's laneChangeMode at SUMO's default;
    ``sumo_tuned``: that and the ego's lane-change parameters ``params``; ``mobil``: the ego's vType
    :data:`MOBIL_EGO_TYPE`)."""
    if name not in ("sumo", "sumo_tuned", "mobil"):
        return env_cfg
    out = copy.deepcopy(env_cfg)
    kwargs = dict(out.kwargs)
    scenario = dict(kwargs.get("scenario") or {})
    if name == "mobil":
        scenario["ego_type"] = MOBIL_EGO_TYPE
    else:
        scenario["ego_lane_change_mode"] = SUMO_DEFAULT_LANE_CHANGE_MODE
    if name == "sumo_tuned":
        scenario["ego_lane_change_params"] = lane_change_entries(params or {})
    kwargs["scenario"] = scenario
    out.kwargs = kwargs
    return out


def evaluate_baseline(
    env_cfg: EnvConfig,
    name: str,
    episodes: int,
    episodes_per_seed: int = 1,
    seed_base: int = EVAL_SEED_BASE,
    gap: GapAcceptanceParams | None = None,
    parallel_envs: int = 1,
    params: Any = None,
) -> EvalResult:
    """Run baseline ``name`` on the evaluation seeds (in this process; one env for SUMO); ``params``: the
    rule's other parameters (:func:`rule_params`: ``mobil``'s MobilParams, ``sumo_tuned``'s dict)."""
    import time

    t0 = time.perf_counter()
    n_streams = math.ceil(episodes / episodes_per_seed)
    seeds = evaluation_seeds(n_streams, seed_base)
    is_sumo = _network(env_cfg) is not None
    name = name.removesuffix(_SHIELD)  # a shielded row: the same rule, the shield is in env_cfg.safety
    if name == "sumo_tuned" and not params:
        raise ValueError("baseline 'sumo_tuned' needs its lane-change parameters (rule_params)")
    envs = [make_env_from_config(baseline_env_config(env_cfg, name, params), seed_base + i)
            for i in range(1 if is_sumo else parallel_envs)]  # fmt: skip
    try:
        by_route = name in ("sumo", "sumo_tuned") and _goal_by_route(env_cfg)
        policy = baseline_policy("keep" if by_route else name, gap, mobil=params if name == "mobil" else None,
                                 n_actions=int(envs[0].action_space.n))  # exit: random draws the speed actions too
        eps = run_episodes(policy, envs, seeds, episodes, episodes_per_seed)
    finally:
        for env in envs:
            env.close()
    return EvalResult(step=0, episodes=eps, seeds=seeds, wall_s=time.perf_counter() - t0)


@dataclass(frozen=True)
class BaselineJob:
    """One baseline evaluation, picklable for a worker process; cached in ``out_dir/evaluation.json``."""

    env_cfg: EnvConfig
    name: str
    episodes: int
    episodes_per_seed: int
    seed_base: int
    gap: GapAcceptanceParams | None
    out_dir: str
    params: Any = None
    """the rule's other parameters (:func:`rule_params`): MobilParams for ``mobil``, a dict for ``sumo_tuned``"""

    def cached(self) -> EvalResult | None:
        path = Path(self.out_dir) / "evaluation.json"
        meta = Path(self.out_dir) / "baseline.json"
        if not (path.is_file() and meta.is_file()):
            return None
        if json.loads(meta.read_text()) != self.meta():
            return None  # other settings: redo
        return EvalResult.load(path)

    def meta(self) -> dict[str, Any]:
        out = {"name": self.name, "env": self.env_cfg.id, "kwargs": self.env_cfg.kwargs, "episodes": self.episodes,
               "episodes_per_seed": self.episodes_per_seed, "seed_base": self.seed_base,
               "gap": None if self.gap is None else self.gap.__dict__}  # fmt: skip
        if self.env_cfg.safety.enabled:  # (absent without a shield: earlier caches stay valid)
            shield, default = to_dict(shield_in_force(self.env_cfg)), to_dict(SafetyConfig())  # with the scenario's fleet
            out["safety"] = {k: v for k, v in shield.items()  # fields added 2026-12-07 only when set: ring caches stay valid
                             if k not in ("unobserved_speed", "unobserved_brake", "lane_end", "beyond_lane") or v != default[k]}
        if self.params is not None:  # (likewise)
            out["params"] = dataclasses.asdict(self.params) if dataclasses.is_dataclass(self.params) else self.params
        return out


def baseline_job(env_cfg: EnvConfig, row: str, episodes: int, episodes_per_seed: int, seed_base: int,
                 out_dir: str | Path, params: Any = None) -> BaselineJob:
    """The :class:`BaselineJob` of table row ``row`` (a baseline's name, ``+shield`` allowed) with its rule's
    frozen parameters ``params`` (:func:`rule_params`)."""
    gap = params if row.removesuffix(_SHIELD) == "gap_acceptance" else None
    return BaselineJob(env_cfg, row, episodes, episodes_per_seed, seed_base, gap, str(out_dir),
                       params=None if gap is not None else params)  # fmt: skip


def _run_job(job: BaselineJob) -> dict[str, Any]:
    res = evaluate_baseline(job.env_cfg, job.name, job.episodes, job.episodes_per_seed, job.seed_base, job.gap,
                            parallel_envs=16, params=job.params)  # fmt: skip
    out = Path(job.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res.save(out / "evaluation.json")
    (out / "baseline.json").write_text(json.dumps(job.meta(), default=str))
    return res.to_json()


def run_baselines(jobs: Sequence[BaselineJob], n_jobs: int | None = None) -> dict[str, EvalResult]:
    """Evaluate the baselines (cached ones are read back), in spawned processes (one libsumo each)."""
    out: dict[str, EvalResult] = {}
    todo = []
    for job in jobs:
        hit = job.cached()
        if hit is not None:
            out[job.out_dir] = hit
        else:
            todo.append(job)
    if todo:
        workers = max(1, min(n_jobs or os.cpu_count() or 1, len(todo)))
        log.info("%d baseline evaluations to run (%d cached), %d in parallel", len(todo), len(jobs) - len(todo), workers)
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            for job, res in zip(todo, pool.map(_run_job, todo)):
                out[job.out_dir] = EvalResult.from_json(res)
                log.info("baseline %s on %s: success %.3f, collision %.3f, return %.2f", job.name, job.env_cfg.id,
                         out[job.out_dir].success_rate, out[job.out_dir].collision_rate,
                         out[job.out_dir].mean_return)  # fmt: skip
    return out


#: the grid of :func:`tune_gap_acceptance` (metres, metres, seconds). Zero margins are in it: on the
#: ring a rule with none and a 0.5 s headway still causes no collision (research/tuning/ring_dqn.md).
GAP_GRID = {"lead_gap": (0.0, 0.5, 1.0), "follow_gap": (0.0, 1.0, 2.0), "time_headway": (0.25, 0.5, 1.0)}


def pick_gap(
    scored: Sequence[tuple[GapAcceptanceParams, EvalResult]], max_collision: float = 0.0
) -> tuple[GapAcceptanceParams, EvalResult]:
    """The tuned thresholds: the highest success among settings whose caused-collision rate is at most
    ``max_collision`` (ties: fewer collisions, then higher return); all settings if none qualifies."""
    if not scored:
        raise ValueError("pick_gap: no scored settings")
    safe = [s for s in scored if s[1].collision_rate <= max_collision] or list(scored)
    return max(safe, key=lambda s: (s[1].success_rate, -s[1].collision_rate, s[1].mean_return))


def tune_gap_acceptance(
    env_cfg: EnvConfig, episodes: int, episodes_per_seed: int, out_dir: str | Path, max_collision: float = 0.0,
    n_jobs: int | None = None,
) -> tuple[GapAcceptanceParams, list[tuple[GapAcceptanceParams, EvalResult]]]:
    """Grid search on the *tuning* evaluation seeds, best by :func:`pick_gap` (by default: the highest
    success with no caused collision; the rule is the bar for safe driving)."""
    grid = [GapAcceptanceParams(*combo) for combo in itertools.product(*GAP_GRID.values())]
    jobs = [BaselineJob(env_cfg, "gap_acceptance", episodes, episodes_per_seed, TUNING_EVAL_SEED_BASE, g,
                        str(Path(out_dir) / f"lead{g.lead_gap}_follow{g.follow_gap}_hw{g.time_headway}"))
            for g in grid]  # fmt: skip
    results = run_baselines(jobs, n_jobs)
    scored = [(g, results[j.out_dir]) for g, j in zip(grid, jobs)]
    return pick_gap(scored, max_collision)[0], scored


# ----------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", nargs="+", help="training YAML(s) whose env the baselines run on")
    parser.add_argument("--episodes", type=int, default=300, help="evaluation episodes per baseline (default 300)")
    parser.add_argument("--tune", action="store_true",
                        help="tune the gap-acceptance thresholds on the tuning seeds instead (writes --out/tuning.md)")  # fmt: skip
    parser.add_argument("--params", default=str(DEFAULT_PARAMS_FILE), help="tuned thresholds (config/baselines.yaml)")
    parser.add_argument("--out", default="runs/baselines", help="folder of the cached evaluations")
    parser.add_argument("--jobs", type=int, default=None, help="parallel processes (default: number of cores)")
    parser.add_argument("--only", action="extend", nargs="+", default=None, metavar="NAME",
                        help="run only these baselines (e.g. immediate gap_acceptance; repeatable; default: all of the env's)")
    parser.add_argument("--tuning-seeds", action="store_true",
                        help="evaluate on the tuning seeds instead of the held-out evaluation seeds")
    parser.add_argument("--safety", choices=SAFETY_KINDS, default="none",
                        help="also run immediate, random and gap acceptance behind this shield (rows '<name>+shield')")
    parser.add_argument("--safety-mode", dest="safety_mode", choices=SAFETY_MODES, default=None,
                        help="replace or mask for the shielded rows (default: the config's env.safety.mode)")


def _cost(value: float) -> str:
    """A cost-to-others cell (EvalResult.mean_time_to_success / mean_imposed_brake): "–" when not measured."""
    return "–" if math.isnan(value) else f"{value:.2f}"


def run(args: argparse.Namespace) -> int:
    lines = ["| Environment | Baseline | Episodes | Success | Caused collision | Time limit | Missed | Mean return "
             "| Interventions / episode | Time to success (s) | Imposed braking (m/s²) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for path in args.config:
        cfg = load_experiment_config(path)
        env_cfg, per_seed = cfg.env, cfg.train.eval_episodes_per_seed
        net = _network(env_cfg)
        if args.tune:
            if net is None:
                raise ConfigError(f"{path}: --tune is for the SUMO lane-change envs, got env.id = {env_cfg.id!r}")
            best, scored = tune_gap_acceptance(env_cfg, args.episodes, per_seed, Path(args.out) / "tuning" / net,
                                               n_jobs=args.jobs)  # fmt: skip
            rows = ["| lead_gap | follow_gap | time_headway | success | caused collision | return |", "|---|---|---|---|---|---|"]
            rows += [f"| {g.lead_gap} | {g.follow_gap} | {g.time_headway} | {r.success_rate:.3f} | {r.collision_rate:.3f} "
                     f"| {r.mean_return:.2f} |" for g, r in sorted(scored, key=lambda s: -s[1].success_rate)]  # fmt: skip
            md = write_markdown(Path(args.out) / "tuning" / f"gap_acceptance_{net}.md", [
                f"# Gap acceptance on {net}: tuning", "",
                f"{args.episodes} episodes per setting on the tuning evaluation seeds ({TUNING_EVAL_SEED_BASE} + k); "
                "best = highest success with no caused collision (ties: higher return).", "",
                f"Best: `{yaml.safe_dump(best.__dict__, default_flow_style=True).strip()}`", "", *rows, ""])  # fmt: skip
            print(md.read_text())
            continue
        names = baseline_names(env_cfg)
        unknown = sorted(set(args.only or ()) - set(names))
        if unknown:
            raise ConfigError(f"--only {unknown[0]!r}: not a baseline of {env_cfg.id}, expected one of {', '.join(names)}")
        chosen = [name for name in names if not args.only or name in args.only]
        shielded = [name for name in SHIELDED_BASELINES if not args.only or name in args.only] if args.safety != "none" else []
        # each rule's frozen parameters, read only for the rules that run (a scenario needs no section for keep)
        params = {name: rule_params(name, net, args.params) for name in {*chosen, *shielded}} if net else {}
        base = TUNING_EVAL_SEED_BASE if args.tuning_seeds else EVAL_SEED_BASE
        sub = "tuning-seeds" if args.tuning_seeds else ""
        folder = Path(args.out) / sub / (net or env_cfg.id)
        jobs = [baseline_job(env_cfg, name, args.episodes, per_seed, base, folder / name, params.get(name))
                for name in chosen]  # fmt: skip
        if shielded and net is not None:
            env_s = shielded_env_config(env_cfg, args.safety, args.safety_mode)
            jobs += [baseline_job(env_s, name + _SHIELD, args.episodes, per_seed, base, folder / (name + _SHIELD),
                                  params.get(name)) for name in shielded]  # fmt: skip
        results = run_baselines(jobs, args.jobs)
        for job in jobs:
            r = results[job.out_dir]
            lines.append(f"| {env_cfg.id} | {job.name} | {r.n} | {r.success_rate:.3f} | {r.collision_rate:.3f} "
                         f"| {r.time_limit_rate:.3f} | {r.rate('missed'):.3f} | {r.mean_return:.2f} "
                         f"| {r.mean_interventions:.2f} | {_cost(r.mean_time_to_success)} | {_cost(r.mean_imposed_brake)} |")  # fmt: skip
    if not args.tune:
        print("\n".join(lines))
    return 0
