"""Where the runs of a suite execute: ``--backend local`` (processes here) or ``--backend ray``.

The tables (``der table1|2|3``) and ``der sweep`` call one function, :func:`run_specs`, with a
backend made from the command line by :func:`backend_from_args`. Every backend leaves each run's
files in ``spec.run_dir`` on this machine, so everything after (tables, figures) is the same.

Rules common to all backends (those of the local suites, :mod:`der_ros.experiments.suite`):
configs are validated here before any run starts; a finished run (``summary.json``) is skipped;
an interrupted one resumes from its ``checkpoint.pt``; a failed run does not stop the others, and
the runs that failed for good are reported together at the end (:class:`SuiteRunError`).
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from der_ros.experiments.backends.artifacts import ARTIFACT_LEVELS
from der_ros.experiments.backends.base import Backend, BackendError, EventSink, RunEvent, RunFailedError
from der_ros.experiments.backends.local import LocalBackend
from der_ros.experiments.backends.ray_cluster import RayBackend
from der_ros.experiments.backends.suite_progress import SuiteProgress
from der_ros.experiments.run_compare import finished_run
from der_ros.experiments.suite import RunSpec, SuiteRunError, UnfinishedRunsError

__all__ = [
    "BACKENDS",
    "Backend",
    "BackendError",
    "LocalBackend",
    "RayBackend",
    "RunEvent",
    "RunFailedError",
    "SuiteRunError",
    "UnfinishedRunsError",
    "add_backend_arguments",
    "backend_from_args",
    "run_specs",
]

log = logging.getLogger(__name__)

BACKENDS = ("local", "ray")


def run_specs(
    specs: Sequence[RunSpec],
    jobs: int | None = None,
    backend: Backend | None = None,
    on_event: EventSink | None = None,
    train: bool = True,
) -> list[dict[str, Any]]:
    """Run the specs that are not finished on ``backend`` (default: ``jobs`` local processes).

    ``train=False`` (``--no-train``): raise :class:`UnfinishedRunsError` if any spec is unfinished.

    Returns the summaries of the runs done now (finished, or interrupted by Ctrl-C); raises
    :class:`SuiteRunError` naming every run that failed for good, after the others are done.
    ``on_event`` sees every :class:`RunEvent` (the progress view sees them too).
    """
    todo = []
    for spec in specs:
        cfg = spec.resolved_config()  # raises ConfigError before any run starts
        if finished_run(Path(spec.run_dir), cfg):  # ConfigError if it holds a run of other settings
            log.info("skip finished run %s", spec.run_dir)
        else:
            todo.append(spec)
    if not todo:
        return []
    if not train:
        raise UnfinishedRunsError(todo, len(specs))
    backend = backend if backend is not None else LocalBackend(jobs)
    log.info("%d runs to do (%d finished), %s", len(todo), len(specs) - len(todo), backend.describe(len(todo)))
    progress = SuiteProgress(len(todo), len(specs) - len(todo))

    def emit(event: RunEvent) -> None:
        progress(event)
        if on_event is not None:
            on_event(event)

    try:
        outcomes = backend.run(todo, emit)
    finally:
        progress.close()
    failures = [(e.spec, e.error or RuntimeError("unknown error")) for e in outcomes if e.kind == "failed"]
    if failures:
        raise SuiteRunError(failures)
    return [e.summary for e in outcomes if e.kind == "finished" and e.summary is not None]


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backend`` and the Ray flags, shared by ``der table1|2|3`` and ``der sweep``."""
    g = parser.add_argument_group("where the runs execute")
    g.add_argument("--backend", choices=BACKENDS, default="local",
                   help="local: processes on this machine (--jobs at a time); ray: Ray tasks, on a local Ray "
                        "instance or a cluster (--address) (default local)")  # fmt: skip
    g.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="Ray cluster to join (started with `ray start --head`; default $RAY_ADDRESS, else a "
                        "local Ray instance with --jobs CPUs); --backend ray only")  # fmt: skip
    g.add_argument("--cpus-per-run", dest="cpus_per_run", type=float, default=None,
                   help="CPUs Ray reserves per run (default 1); --backend ray only")  # fmt: skip
    g.add_argument("--gpus-per-run", dest="gpus_per_run", type=float, default=None,
                   help="GPUs per run, fractions share a GPU (default 1 with train.device cuda, else 0); "
                        "--backend ray only")  # fmt: skip
    g.add_argument("--resources-per-run", dest="resources_per_run", default=None, metavar="JSON",
                   help='custom Ray resources per run, e.g. \'{"sumo": 1}\' to use only nodes started with '
                        '--resources \'{"sumo": 8}\'; --backend ray only')  # fmt: skip
    g.add_argument("--max-retries", dest="max_retries", type=int, default=None,
                   help="times a run is retried when its worker dies (killed, node lost), from its last "
                        "checkpoint that reached this machine (default 2); --backend ray only")  # fmt: skip
    g.add_argument("--artifacts", choices=ARTIFACT_LEVELS, default=None,
                   help="files sent back per run: small (CSVs, summary, config, evaluation), checkpoint "
                        "(+ checkpoint.pt, the final and periodic ones; default), all (+ tb/); --backend ray only")  # fmt: skip


_RAY_ONLY = ("address", "cpus_per_run", "gpus_per_run", "resources_per_run", "max_retries", "artifacts")


def backend_from_args(args: argparse.Namespace, jobs: int | None = None) -> Backend:
    """The backend the flags ask for; a Ray flag without ``--backend ray`` is an error naming it.

    ``jobs``: parallel runs of the local backend when the caller computed them (default ``--jobs``).
    """
    if args.backend == "local":
        given = [n for n in _RAY_ONLY if getattr(args, n, None) is not None]
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise BackendError(f"{flag} applies to --backend ray only (the backend is local)")
        return LocalBackend(jobs if jobs is not None else args.jobs)
    resources: dict[str, float] = {}
    if args.resources_per_run:
        try:
            resources = json.loads(args.resources_per_run)
            if not isinstance(resources, dict) or not all(isinstance(v, (int, float)) for v in resources.values()):
                raise ValueError("not a mapping of names to numbers")
        except ValueError as exc:
            raise BackendError(f"--resources-per-run {args.resources_per_run!r}: expected a JSON object like "
                               f'\'{{"sumo": 1}}\' ({exc})') from None  # fmt: skip
    return RayBackend(
        address=args.address,
        num_cpus=args.jobs,
        cpus_per_run=1.0 if args.cpus_per_run is None else args.cpus_per_run,
        gpus_per_run=args.gpus_per_run,
        resources=resources,
        max_retries=2 if args.max_retries is None else args.max_retries,
        artifacts=args.artifacts or "checkpoint",
    )
