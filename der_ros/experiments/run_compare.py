"""Is this the same finished run? The one answer, for the suites, their backends and the benchmarks.

Three questions, one function each:

* **Same settings** (:func:`check_same_settings`): a run directory's ``config.yaml`` holds the
  settings of ``cfg``, apart from where and how the run is written or shown
  (:data:`NOT_RESULT_FIELDS`); a SUMO scenario field missing there, added after the run was made,
  counts as its default (:func:`resolved_settings`). Other settings raise a ``ConfigError`` naming
  the fields, so a changed config with an old ``--out`` is never reported under the new settings.
* **Finished** (:func:`finished_run`): same settings, and ``summary.json`` says the run reached
  ``train.total_steps`` without an interruption. The suites skip such a run and resume any other.
* **Same files** (:func:`comparable_run`, :func:`run_differences`): two runs of one spec, on any
  backend or machine, after any resumption, wrote the same files apart from timings.

Training is deterministic per seed on CPU (one torch thread, seeded env, agent and replay
RNGs), so two runs of the same spec write the same files bit for bit, except for what measures
time. :func:`comparable_run` reads a run directory and drops exactly that:

* ``episodes.csv``: every column but ``wall_time``;
* ``metrics.csv``: every row but ``charts/steps_per_s``, every column but ``wall_time``; rows are
  sorted by (step, name), because SUMO runs evaluate in a second process and write the ``eval/*``
  rows when the result arrives (same values, the position in the file depends on timing);
* ``evaluations.csv`` without ``wall_s``; ``evaluation.json`` without its ``wall_s`` fields;
* ``summary.json`` without ``wall_time_s`` and ``steps_per_s``;
* ``config.yaml``, ``command.txt`` as text; ``checkpoint.pt``: every tensor and array of the agent
  (online and target networks, optimizer, replay storage and sampler state, its RNG states,
  counters), the runner's counters except ``wall_time``, and the pickled environment without the
  wall-clock fields of gymnasium's ``RecordEpisodeStatistics``. Not compared: ``torch_rng``, the
  process-wide torch generator saved for resuming. Training never draws from it (initial weights
  come from a forked generator), so its state only records what ran before in the worker
  process, and both backends reuse worker processes.

Paths are compared relative to the output folder (``root``), so ``--out A`` and ``--out B`` agree.
Where it is *not* deterministic: CUDA (``--device cuda``: cuDNN and atomics reorder float sums),
more than one torch thread (``train.threads``), and anything timed (the columns above).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.configuration import ConfigError, flatten_names, to_dict
from der_ros.train.config import ExperimentConfig, load_experiment_config
from sumo_bridge import ENV_NETWORKS
from sumo_bridge.scenario_file import scenario_from_kwargs

__all__ = [
    "NOT_RESULT_FIELDS",
    "resolved_settings",
    "check_same_settings",
    "finished_run",
    "comparable_run",
    "run_differences",
    "TIMING_METRICS",
]

# ----------------------------------------------------------------------------- same settings, finished
#: settings that say where and how a run is written or shown, not what it computes
NOT_RESULT_FIELDS = frozenset(
    f"train.{name}"
    for name in (
        "run_dir",
        "runs_root",
        "progress",
        "device",
        "threads",
        "env_process",
        "log_interval",
        "checkpoint_interval",
        "tensorboard",
        "save_final_checkpoint",
    )
)


def resolved_settings(cfg: ExperimentConfig) -> dict[str, Any] | None:
    """``cfg.to_dict()`` with a SUMO scenario completed by its defaults (None: the current code
    cannot read that scenario, e.g. a field since removed).

    The env's keyword arguments are stored as written, so a scenario field added after a run was made
    is missing from that run's ``config.yaml``; completed here, "missing" and "the default" compare
    equal (new fields default to the behaviour that came before them).
    """
    data = cfg.to_dict()
    network = ENV_NETWORKS.get(cfg.env.id)
    kwargs = data["env"]["kwargs"]
    if network is None or not isinstance(kwargs, dict) or set(kwargs) - {"scenario", "render_mode"}:
        return data
    try:
        scenario = to_dict(scenario_from_kwargs(network, dict(kwargs.get("scenario") or {})))
    except ConfigError:
        return None
    data["env"]["kwargs"] = {**kwargs, "scenario": scenario}
    return data


def check_same_settings(run_dir: Path, cfg: ExperimentConfig) -> None:
    """Refuse to reuse or resume a run directory made with other settings (its ``config.yaml``).

    A finished run is otherwise skipped whatever the config says, so a changed config file with an
    old ``--out`` would quietly report the old runs under the new settings.
    """
    saved = run_dir / "config.yaml"
    if not saved.is_file():
        return
    saved_cfg = load_experiment_config(saved)
    old, new = resolved_settings(saved_cfg), resolved_settings(cfg)
    if old is None or new is None:  # one side unreadable today: compare both as written
        old, new = saved_cfg.to_dict(), cfg.to_dict()
    old, new = flatten_names(old), flatten_names(new)
    changed = sorted(k for k in old.keys() | new.keys() if k not in NOT_RESULT_FIELDS and old.get(k) != new.get(k))
    if changed:
        shown = "; ".join(f"{k} = {old.get(k)!r} there, {new.get(k)!r} now" for k in changed[:5])
        more = f" (and {len(changed) - 5} more)" if len(changed) > 5 else ""
        raise ConfigError(
            f"{run_dir} holds a run made with other settings: {shown}{more}. "
            "Use another --out, or delete that run directory to redo it."
        )


def finished_run(run_dir: Path, cfg: ExperimentConfig) -> bool:
    """Whether ``run_dir`` holds a finished run of ``cfg``; a run of other settings raises ConfigError.

    Finished: ``summary.json`` (written by :func:`der_ros.train.runner.train`) reports
    ``cfg.train.total_steps`` steps or more and no interruption. A missing or unreadable summary is
    not finished (the run resumes from its checkpoint, or starts again)."""
    check_same_settings(run_dir, cfg)
    total_steps = cfg.train.total_steps
    path = run_dir / "summary.json"
    if not path.is_file():
        return False
    try:
        s = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return not s.get("interrupted", True) and int(s.get("steps", 0)) >= total_steps


# ----------------------------------------------------------------------------- same files
#: metrics.csv rows that measure speed
TIMING_METRICS = ("charts/steps_per_s",)


def _normalize(text: str, root: str) -> str:
    return text.replace(root, "<out>")


def _csv_rows(path: Path, drop: tuple[str, ...]) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(fh)]


def _metrics(path: Path) -> list[tuple[int, str, str]]:
    rows = [(int(r["step"]), r["name"], r["value"]) for r in _csv_rows(path, ("wall_time",))
            if r["name"] not in TIMING_METRICS]  # fmt: skip
    return sorted(rows, key=lambda r: (r[0], r[1]))


def _without_wall(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _without_wall(v) for k, v in obj.items() if k != "wall_s"}
    if isinstance(obj, list):
        return [_without_wall(v) for v in obj]
    return obj


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _canonical(obj: Any, root: str) -> Any:
    """Tensors and arrays as (dtype, shape, sha256 of the bytes); strings with ``root`` normalized."""
    import torch

    if isinstance(obj, torch.Tensor):
        arr = obj.detach().cpu().contiguous()
        raw = arr.reshape(-1).view(torch.uint8).numpy().tobytes()
        return ("tensor", str(arr.dtype), tuple(arr.shape), _digest(raw))
    if isinstance(obj, np.ndarray):
        return ("array", obj.dtype.str, obj.shape, _digest(np.ascontiguousarray(obj).tobytes()))
    if isinstance(obj, dict):
        return {str(k): _canonical(v, root) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v, root) for v in obj]
    if isinstance(obj, bytes):
        return ("bytes", _digest(obj))
    if isinstance(obj, str):
        return _normalize(obj, root)
    if isinstance(obj, float):
        return repr(obj)
    if obj is None or isinstance(obj, (bool, int)):
        return obj
    return ("object", type(obj).__name__, _digest(pickle.dumps(obj, protocol=4)))


#: gymnasium's RecordEpisodeStatistics keeps wall-clock times (episode start, recent durations)
_ENV_TIMING = {"episode_start_time": 0.0, "time_queue": None}


def _env_without_timing(data: bytes) -> str:
    """Digest of a pickled environment with its wall-clock fields cleared."""
    env = pickle.loads(data)
    layer = env
    while layer is not None:
        for name, blank in _ENV_TIMING.items():
            if name in vars(layer):
                old = vars(layer)[name]
                setattr(layer, name, type(old)(maxlen=old.maxlen) if blank is None else blank)
        layer = vars(layer).get("env")
    return _digest(pickle.dumps(env, protocol=4))


def _checkpoint(path: Path, root: str) -> Any:
    import torch

    ckpt = torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=False)
    agent = {k: v for k, v in ckpt["agent"].items() if k != "torch_rng"}
    runner = dict(ckpt.get("extra", {}).get("runner", {}))
    runner.pop("wall_time", None)
    extra = {k: v for k, v in ckpt.get("extra", {}).items() if k not in ("runner", "env")}
    env = ckpt.get("extra", {}).get("env")
    return {"agent": _canonical(agent, root), "runner": _canonical(runner, root), "extra": _canonical(extra, root),
            "env": _env_without_timing(env) if env is not None else None}  # fmt: skip


def comparable_run(run_dir: str | Path, root: str | Path) -> dict[str, Any]:
    """The parts of a run directory that must be identical between two runs of the same spec."""
    run = Path(run_dir)
    root_s = str(root)
    out: dict[str, Any] = {}
    if (run / "episodes.csv").is_file():
        out["episodes.csv"] = _csv_rows(run / "episodes.csv", ("wall_time",))
    if (run / "metrics.csv").is_file():
        out["metrics.csv"] = _metrics(run / "metrics.csv")
    if (run / "evaluations.csv").is_file():
        out["evaluations.csv"] = _csv_rows(run / "evaluations.csv", ("wall_s",))
    if (run / "evaluation.json").is_file():
        out["evaluation.json"] = _without_wall(json.loads((run / "evaluation.json").read_text()))
    if (run / "summary.json").is_file():
        summary = json.loads((run / "summary.json").read_text())
        out["summary.json"] = {k: _canonical(v, root_s) for k, v in summary.items()
                               if k not in ("wall_time_s", "steps_per_s")}  # fmt: skip
    for name in ("config.yaml", "command.txt"):
        if (run / name).is_file():
            out[name] = _normalize((run / name).read_text(), root_s)
    if (run / "checkpoint.pt").is_file():
        out["checkpoint.pt"] = _checkpoint(run / "checkpoint.pt", root_s)
    return out


def run_differences(a: str | Path, a_root: str | Path, b: str | Path, b_root: str | Path) -> list[str]:
    """Names of the files (and how) in which two run directories differ; empty when identical."""
    ca, cb = comparable_run(a, a_root), comparable_run(b, b_root)
    diffs = []
    for name in sorted(set(ca) | set(cb)):
        if name not in ca or name not in cb:
            diffs.append(f"{name}: only in {a if name in ca else b}")
        elif ca[name] != cb[name]:
            diffs.append(f"{name}: differs")
    return diffs
