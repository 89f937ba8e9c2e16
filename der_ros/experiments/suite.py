"""Generic multi-seed experiment suite: methods x seeds -> training runs in parallel processes.

Environment-agnostic: Table 1 (CartPole), Table 2 (Atari) and Table 3 (SUMO) all use it. A run
is one ``der train``-equivalent call (config file + dotted overrides) in a worker process, writing
its own run directory ``<out>/<method>/seed<k>/`` (``<out>/<group>/<method>/seed<k>/`` with
groups, e.g. one per Atari game). The suite is resumable:

* a run whose ``summary.json`` says it finished ``total_steps`` is skipped;
* a run with a ``checkpoint.pt`` but no finished summary (killed, Ctrl-C) resumes from it;
* anything else starts fresh.

Either way the run directory's ``config.yaml`` must hold the same settings (apart from where and how
the run is written or shown; a SUMO scenario field missing there, added after the run was made,
counts as its default): a run made with other settings is refused with a ``ConfigError`` naming the
fields, never reported under the new ones. Both rules, "finished" and "same settings", are
:func:`der_ros.experiments.run_compare.finished_run`.

Ctrl-C: every worker gets the SIGINT too, finishes its current step, writes a checkpoint and
stops; queued runs are cancelled. Rerunning the same command continues where it stopped.

This module plans runs and executes one (:func:`run_one`); :mod:`der_ros.experiments.backends`
executes many, as local processes or as Ray tasks (``--backend``), with the rules above.
"""

from __future__ import annotations

import json
import logging
import os
import shlex
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import der_ros
from der_ros.experiments.run_compare import finished_run
from der_ros.train.config import ExperimentConfig, add_set_argument, load_experiment_config, parse_assignments
from der_ros.train.metrics import read_episodes_csv, read_metrics_csv

__all__ = [
    "Method",
    "PAPER_METHODS",
    "methods_by_name",
    "shielded_method",
    "SHIELD_SUFFIX",
    "RunSpec",
    "RunResult",
    "plan_runs",
    "run_one",
    "SuiteRunError",
    "load_result",
    "default_jobs",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Method:
    """One column of the paper's tables: a name for paths, a label for tables, config overrides."""

    name: str
    label: str
    overrides: tuple[tuple[str, Any], ...]


#: The five methods of Tables 1-3, in the paper's row order. Only the replay differs (section 4.1).
PAPER_METHODS: tuple[Method, ...] = (
    Method("dqn", "DQN", (("replay.kind", "uniform"),)),
    Method("der0.1", "λ = 0.1", (("replay.kind", "der"), ("replay.lam", 0.1))),
    Method("der0.5", "λ = 0.5", (("replay.kind", "der"), ("replay.lam", 0.5))),
    Method("der0.9", "λ = 0.9", (("replay.kind", "der"), ("replay.lam", 0.9))),
    Method("per", "PER", (("replay.kind", "per"),)),
)


#: suffix of a method run behind the safety shield (``dqn+shield``; docs/safety.md)
SHIELD_SUFFIX = "+shield"


def shielded_method(method: Method, kind: str, mode: str | None = None) -> Method:
    """``method`` behind the shield ``kind`` (env.safety): name ``<name>+shield``, same replay settings."""
    overrides = (*method.overrides, ("env.safety.kind", kind))
    if mode is not None:
        overrides += (("env.safety.mode", mode),)
    return Method(method.name + SHIELD_SUFFIX, f"{method.label} + shield", overrides)


def methods_by_name(names: Iterable[str] | None) -> list[Method]:
    """Pick methods of :data:`PAPER_METHODS` by name (``None`` = all, in paper order)."""
    if names is None:
        return list(PAPER_METHODS)
    known = {m.name: m for m in PAPER_METHODS}
    out = []
    for n in names:
        if n not in known:
            raise ValueError(f"method {n!r} unknown; expected one of {', '.join(known)}")
        out.append(known[n])
    return out


@dataclass(frozen=True)
class RunSpec:
    """One training run of a suite; picklable so a worker process can execute it."""

    method: Method
    seed: int
    config_path: str
    run_dir: str
    overrides: tuple[tuple[str, Any], ...] = ()
    group: str = ""

    def all_overrides(self) -> dict[str, Any]:
        """File < method < suite overrides; seed and run_dir are always set; no progress bar."""
        out: dict[str, Any] = dict(self.method.overrides)
        out.update(dict(self.overrides))
        out["train.seed"] = self.seed
        out["train.run_dir"] = self.run_dir
        out["train.progress"] = False
        return out

    def resolved_config(self) -> ExperimentConfig:
        """The run's config: the file with :meth:`all_overrides` applied (ConfigError if it is invalid)."""
        return load_experiment_config(self.config_path, self.all_overrides())

    def command(self) -> str:
        """The equivalent ``der train`` command line (written to the run directory)."""
        parts = ["der", "train", "--config", self.config_path]
        for k, v in self.all_overrides().items():
            parts += ["--set", f"{k}={json.dumps(v) if not isinstance(v, str) else v}"]
        return shlex.join(parts)


@dataclass
class RunResult:
    """A finished run read back from its directory."""

    spec: RunSpec
    summary: dict[str, Any]
    episode_steps: np.ndarray
    returns: np.ndarray
    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def run_one(
    spec: RunSpec,
    run_dir: str | Path | None = None,
    cfg: Any = None,
    on_checkpoint: Callable[[Path, int], None] | None = None,
) -> dict[str, Any]:
    """Execute (or skip, or resume) one run; returns its summary as a dict. Top level: picklable.

    ``run_dir`` is where the files are written (default ``spec.run_dir``): the Ray backend runs in
    a temporary folder of its worker and ships the files to ``spec.run_dir`` on the driver. ``cfg``
    is the resolved config (default: read ``spec.config_path``), for workers that do not have the
    driver's config file. ``on_checkpoint`` goes to :func:`der_ros.train.runner.train`.
    """
    import torch

    from der_ros.train.runner import CHECKPOINT_NAME, train

    torch.set_num_threads(1)
    cfg = cfg if cfg is not None else spec.resolved_config()
    run_dir = Path(run_dir if run_dir is not None else spec.run_dir)
    if finished_run(run_dir, cfg):
        return json.loads((run_dir / "summary.json").read_text()) | {"skipped": True}
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "command.txt").write_text(spec.command() + "\n")
    ckpt = run_dir / CHECKPOINT_NAME
    resume = ckpt if ckpt.is_file() else None
    summary = train(cfg, run_dir=run_dir, resume=resume, on_checkpoint=on_checkpoint)
    return dict(summary.__dict__)


def default_jobs() -> int:
    """Worker processes: the number of CPU cores available to this process."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def plan_runs(
    config_path: str | Path,
    methods: Sequence[Method],
    seeds: Sequence[int],
    out_dir: str | Path,
    overrides: dict[str, Any] | None = None,
    group: str = "",
) -> list[RunSpec]:
    """RunSpecs for every (method, seed); ``overrides`` (dotted keys) apply to all of them."""
    base = Path(out_dir) / group if group else Path(out_dir)
    ov = tuple((overrides or {}).items())
    return [
        RunSpec(m, int(s), str(config_path), str(base / m.name / f"seed{s}"), ov, group) for m in methods for s in seeds
    ]


class SuiteRunError(RuntimeError):
    """Some runs of a suite raised; the others finished and are kept (a rerun redoes only these)."""

    user_facing = True

    def __init__(self, failures: Sequence[tuple[RunSpec, BaseException]]) -> None:
        self.failures = list(failures)
        lines = [f"{len(self.failures)} run(s) failed (the others finished; rerun the same command to retry these):"]
        lines += [f"  {spec.run_dir}: {type(exc).__name__}: {exc}" for spec, exc in self.failures]
        super().__init__("\n".join(lines))


class UnfinishedRunsError(RuntimeError):
    """``--no-train``: some runs of a suite are not finished, and the suite was told not to train them."""

    user_facing = True

    def __init__(self, specs: Sequence[RunSpec], total: int) -> None:
        self.specs = list(specs)
        lines = [f"{len(self.specs)} of {total} runs are not finished and --no-train was given "
                 "(drop it to train them, or point --out at the folder that holds the finished runs):"]  # fmt: skip
        lines += [f"  {spec.run_dir}" for spec in self.specs[:10]]
        if len(self.specs) > 10:
            lines.append(f"  ... and {len(self.specs) - 10} more")
        super().__init__("\n".join(lines))


def load_result(spec: RunSpec, metric_names: Iterable[str] | None = None) -> RunResult:
    """Read a finished run's summary, episodes and (optionally only some) metrics."""
    run_dir = Path(spec.run_dir)
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise FileNotFoundError(f"run {run_dir} has no summary.json (not run or still running)")
    summary = json.loads(summary_path.read_text())
    ep = read_episodes_csv(run_dir / "episodes.csv")
    metrics: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    mpath = run_dir / "metrics.csv"
    if mpath.is_file():
        wanted = set(metric_names) if metric_names is not None else None
        for name, (steps, values) in read_metrics_csv(mpath).items():
            if wanted is None or name in wanted:
                metrics[name] = (np.asarray(steps, dtype=np.int64), np.asarray(values, dtype=np.float64))
    return RunResult(
        spec=spec,
        summary=summary,
        episode_steps=np.asarray(ep["step"], dtype=np.float64),
        returns=np.asarray(ep["return"], dtype=np.float64),
        metrics=metrics,
    )


# ----------------------------------------------------------------------------- CLI helpers
#: First training seed of the published tables (the report seeds; tuning uses 100.., `der sweep`'s default).
REPORT_FIRST_SEED = 1000


def add_suite_arguments(
    parser: Any, default_config: str, default_out: str, default_seeds: int = 5, default_steps: int | None = None
) -> None:
    """Flags shared by ``der table1/2/3``: config, seeds, steps, jobs, methods, output folders.

    ``default_config`` is relative to the working directory, or else to the source checkout.
    """
    if not Path(default_config).is_file():
        candidate = Path(__file__).resolve().parents[2] / default_config
        if candidate.is_file():
            default_config = str(candidate)
    parser.add_argument("--config", default=default_config, help=f"training YAML (default {default_config})")
    parser.add_argument("--seeds", type=int, default=default_seeds, help=f"seeds per method (default {default_seeds})")
    parser.add_argument("--first-seed", dest="first_seed", type=int, default=REPORT_FIRST_SEED,
                        help=f"seeds are first..first+seeds-1 (default {REPORT_FIRST_SEED}: the report seeds)")  # fmt: skip
    parser.add_argument(
        "--steps",
        type=int,
        default=default_steps,
        help="environment steps per run (default: " + (f"{default_steps}" if default_steps else "the config's") + ")",
    )
    parser.add_argument("--jobs", type=int, default=None, help="parallel runs (default: number of cores)")
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        choices=[m.name for m in PAPER_METHODS],
        help="subset of methods (default: all five of the paper)",
    )
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None, help="torch device of every run")
    parser.add_argument("--out", default=default_out, help=f"folder of the run directories (default {default_out})")
    parser.add_argument("--results", default="results", help="folder for the table (.md) and figures (.png)")
    parser.add_argument("--no-train", dest="train", action="store_false",
                        help="only re-table finished runs: stop, naming the unfinished ones, instead of training them")  # fmt: skip
    add_set_argument(parser, help="config override for every run; VALUE is YAML (repeatable)")


def suite_overrides(args: Any) -> dict[str, Any]:
    """Dotted overrides from the shared suite flags (``--steps``, ``--device``, ``--set``)."""
    out: dict[str, Any] = {}
    if args.steps is not None:
        out["train.total_steps"] = int(args.steps)
    if args.device is not None:
        out["train.device"] = args.device
    out.update(parse_assignments(args.set_values, "command line", label="--set"))
    return out


def suite_seeds(args: Any) -> list[int]:
    """The seeds of a suite: ``--first-seed`` up to ``--first-seed + --seeds - 1``."""
    return list(range(args.first_seed, args.first_seed + args.seeds))


def report_interrupted(name: str, summaries: Iterable[dict[str, Any]]) -> bool:
    """True, after telling the user how to continue, if a run of ``der <name>`` was interrupted."""
    if not any(s.get("interrupted") for s in summaries):
        return False
    import sys

    print(f"der {name}: interrupted; runs saved checkpoints, rerun the same command to continue", file=sys.stderr)
    return True


def suite_command(name: str, args: Any, extra: Sequence[str] = ()) -> str:
    """The canonical command line that reproduces a suite (written into the results file)."""
    parts = [
        "der",
        name,
        "--config",
        str(args.config),
        "--seeds",
        str(args.seeds),
        "--first-seed",
        str(args.first_seed),
    ]
    if args.steps is not None:
        parts += ["--steps", str(args.steps)]
    if args.jobs is not None:
        parts += ["--jobs", str(args.jobs)]
    if args.methods:
        parts += ["--methods", *args.methods]
    if args.device:
        parts += ["--device", args.device]
    parts += ["--out", str(args.out), "--results", str(args.results), *extra]
    for s in args.set_values:
        parts += ["--set", s]
    return shlex.join(parts)


def environment_info() -> dict[str, str]:
    """Versions and machine facts for the results files."""
    import platform
    import sys
    from datetime import datetime, timezone

    import gymnasium
    import torch

    return {
        "date (UTC)": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M"),
        "der_ros": der_ros.__version__,
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "gymnasium": gymnasium.__version__,
        "numpy": np.__version__,
        "machine": f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPUs"
        + (f", CUDA {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ", no CUDA"),
    }
