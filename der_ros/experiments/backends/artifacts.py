"""A run's files as bytes: how a run done on another machine reaches the driver's ``--out``.

Workers of the Ray backend may share no file system with the driver, so a worker trains into a
temporary folder of its own and sends the files back as ``{relative path: bytes}``; the driver
writes them where the local backend would have written them. How much is sent is the
``--artifacts`` level:

* ``small``: summary, config, command, metrics/episodes/evaluations CSVs, evaluation.json;
* ``checkpoint`` (default): small + ``checkpoint.pt`` (the final one, and the periodic ones a
  retried run resumes from);
* ``all``: checkpoint + ``tb/`` (TensorBoard event files).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path, PurePosixPath

from der_ros.train.runner import CHECKPOINT_NAME

__all__ = ["ARTIFACT_LEVELS", "RESUME_FILES", "collect_files", "write_files", "relocate_summary"]

ARTIFACT_LEVELS = ("small", "checkpoint", "all")
#: what a run needs to resume: the checkpoint and the files the resumed run appends to
RESUME_FILES = (CHECKPOINT_NAME, "metrics.csv", "episodes.csv", "evaluations.csv")
_TB = "tb"


def _wanted(rel: str, level: str) -> bool:
    parts = PurePosixPath(rel).parts
    if any(p.startswith(".") for p in parts):  # temporary files of atomic writes
        return False
    if rel == CHECKPOINT_NAME:
        return level != "small"
    if parts[0] == _TB:
        return level == "all"
    return True


def collect_files(run_dir: str | Path, level: str, only: tuple[str, ...] | None = None) -> dict[str, bytes]:
    """The files of ``run_dir`` at ``level`` (``only``: just these names, plus ``tb/`` at 'all')."""
    if level not in ARTIFACT_LEVELS:
        raise ValueError(f"--artifacts {level!r}: expected one of {', '.join(ARTIFACT_LEVELS)}")
    root = Path(run_dir)
    out: dict[str, bytes] = {}
    if not root.is_dir():
        return out
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if not path.is_file() or not _wanted(rel, level):
            continue
        if only is not None and rel not in only and not rel.startswith(_TB + "/"):
            continue
        out[rel] = path.read_bytes()
    return out


def write_files(run_dir: str | Path, files: Mapping[str, bytes]) -> None:
    """Write ``files`` under ``run_dir``, each atomically (a reader never sees half a file)."""
    root = Path(run_dir)
    for rel, data in files.items():
        parts = PurePosixPath(rel).parts
        if PurePosixPath(rel).is_absolute() or ".." in parts or not parts:
            raise ValueError(f"artifact path {rel!r} leaves the run directory")
        path = root.joinpath(*parts)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.part{os.getpid()}")
        tmp.write_bytes(data)
        tmp.replace(path)


def relocate_summary(data: bytes, run_dir: str) -> bytes:
    """``summary.json`` of a run trained in a worker's folder, as if trained in ``run_dir``.

    The runner records its own folder (``run_dir``, ``checkpoint``); the rest is kept as is, and
    the text is formatted as the runner formats it, so the file is the one a local run writes.
    """
    summary = json.loads(data)
    summary["run_dir"] = str(Path(run_dir))
    if summary.get("checkpoint"):
        summary["checkpoint"] = str(Path(run_dir) / CHECKPOINT_NAME)
    return json.dumps(summary, indent=2, default=float).encode()
