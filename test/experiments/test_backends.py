"""Backends without a Ray cluster: flags, artifacts, progress lines, run identity, env closing.

The Ray tests proper (local instance, two nodes, killed worker, SUMO in a reused worker) are in
``test_ray_backend.py`` and ``test_ray_cluster.py``.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import shutil
import sys
from pathlib import Path

import pytest

from der_ros import cli
from der_ros.experiments.backends.artifacts import collect_files, relocate_summary, write_files
from der_ros.experiments.backends.dispatch import (
    BackendError,
    LocalBackend,
    RayBackend,
    RunEvent,
    add_backend_arguments,
    backend_from_args,
)
from der_ros.experiments.backends.suite_progress import SuiteProgress
from der_ros.experiments.run_compare import comparable_run, run_differences
from der_ros.experiments.suite import PAPER_METHODS, plan_runs
from der_ros.train.config import load_experiment_config
from der_ros.train.runner import train

REPO = Path(__file__).resolve().parents[2]
CARTPOLE = REPO / "config" / "cartpole.yaml"


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--jobs", type=int, default=None)
    add_backend_arguments(parser)
    return parser.parse_args(list(argv))


def test_backend_flags() -> None:
    assert isinstance(backend_from_args(_parse()), LocalBackend)
    assert backend_from_args(_parse("--jobs", "3")).jobs == 3
    ray = backend_from_args(_parse("--backend", "ray", "--jobs", "2", "--gpus-per-run", "0.25", "--max-retries", "5",
                                   "--artifacts", "small", "--resources-per-run", '{"sumo": 1}'))  # fmt: skip
    assert isinstance(ray, RayBackend)
    assert (ray.num_cpus, ray.gpus_per_run, ray.max_retries, ray.artifacts, ray.resources) == (
        2, 0.25, 5, "small", {"sumo": 1})  # fmt: skip
    opts = ray.task_options({"train": {"device": "cpu"}})
    assert opts["num_cpus"] == 1.0 and opts["num_gpus"] == 0.25 and opts["max_retries"] == 0
    assert opts["resources"] == {"sumo": 1}
    # a GPU per run by default for cuda runs, none for CPU runs
    default = backend_from_args(_parse("--backend", "ray"))
    assert default.task_options({"train": {"device": "cuda"}})["num_gpus"] == 1.0
    assert default.task_options({"train": {"device": "cpu"}})["num_gpus"] == 0.0
    assert default.artifacts == "checkpoint" and default.max_retries == 2
    with pytest.raises(BackendError, match="--address applies to --backend ray only"):
        backend_from_args(_parse("--address", "127.0.0.1:6379"))
    with pytest.raises(BackendError, match="--max-retries applies to --backend ray only"):
        backend_from_args(_parse("--max-retries", "1"))
    with pytest.raises(BackendError, match="--resources-per-run"):
        backend_from_args(_parse("--backend", "ray", "--resources-per-run", "[1, 2]"))
    with pytest.raises(BackendError, match="--max-retries -1"):
        backend_from_args(_parse("--backend", "ray", "--max-retries", "-1"))


def test_backend_ray_without_ray_is_one_clear_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    argv = ["sweep", str(CARTPOLE), "--seeds", "1", "--out", str(tmp_path), "--backend", "ray",
            "--set", "train.total_steps=100"]  # fmt: skip
    assert cli.main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("der sweep: --backend ray: the ray package is not installed")
    assert "--backend local" in err[-1]
    assert not list(tmp_path.rglob("summary.json"))  # nothing ran


def test_artifacts_levels_and_relocation(tmp_path: Path) -> None:
    run = tmp_path / "worker" / "run"
    (run / "tb").mkdir(parents=True)
    for name in ("metrics.csv", "episodes.csv", "checkpoint.pt", "config.yaml", ".summary.json.tmp", "tb/events.1"):
        (run / name).write_bytes(name.encode())
    assert set(collect_files(run, "small")) == {"metrics.csv", "episodes.csv", "config.yaml"}
    assert set(collect_files(run, "checkpoint")) == {"metrics.csv", "episodes.csv", "config.yaml", "checkpoint.pt"}
    assert "tb/events.1" in collect_files(run, "all")
    assert set(collect_files(run, "checkpoint", ("checkpoint.pt", "metrics.csv"))) == {"checkpoint.pt", "metrics.csv"}
    with pytest.raises(ValueError, match="--artifacts 'most'"):
        collect_files(run, "most")
    dest = tmp_path / "out" / "dqn" / "seed0"
    write_files(dest, collect_files(run, "all"))
    assert (dest / "tb" / "events.1").read_bytes() == b"tb/events.1"
    assert not list(dest.rglob(".*"))  # no temporary file left behind
    with pytest.raises(ValueError, match="leaves the run directory"):
        write_files(dest, {"../escape": b"x"})
    summary = {"run_dir": str(run), "steps": 3, "wall_time_s": 1.5, "checkpoint": str(run / "checkpoint.pt"),
               "eval_return": float("nan")}  # fmt: skip
    moved = json.loads(relocate_summary(json.dumps(summary, indent=2).encode(), "runs/x/seed0"))
    assert moved["run_dir"] == "runs/x/seed0" and moved["checkpoint"] == "runs/x/seed0/checkpoint.pt"
    assert moved["steps"] == 3 and moved["wall_time_s"] == 1.5


def test_progress_plain_lines(caplog: pytest.LogCaptureFixture) -> None:
    specs = plan_runs("cfg.yaml", PAPER_METHODS[:1], [0, 1], "/out")
    progress = SuiteProgress(total=2, finished_before=3, stream=io.StringIO())  # not a terminal: log lines
    with caplog.at_level(logging.INFO, logger="der_ros.experiments.progress"):
        progress(RunEvent("started", specs[0], where={"host": "h1", "node": "abcdef123456", "pid": 7}))
        progress(RunEvent("started", specs[1]))
        progress(RunEvent("checkpoint", specs[0], step=100))  # changes no count: no line
        progress(RunEvent("retry", specs[0], 1, error=RuntimeError("WorkerCrashedError: gone"), step=100))
        progress(RunEvent("finished", specs[1], summary={"steps": 10, "episodes": 2, "mean_return": 5.0}))
        progress(RunEvent("failed", specs[0], 1, error=ValueError("bad")))
        progress.close()
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "[0/2] start dqn seed 0 on h1 (node abcdef12, pid 7) | 1 running, 0 failed, ETA -"
    assert lines[2].startswith("[0/2] retry dqn seed 0 from its checkpoint at step 100 (attempt 2)")
    assert lines[3].startswith("[1/2] dqn seed 1: 10 steps, 2 episodes, mean return 5.00 | 0 running, 0 failed, 1 retried, ETA ")
    assert "ETA" in lines[3] and "ETA -" not in lines[3]
    assert lines[4].startswith("[2/2] run /out/dqn/seed0 failed: ValueError: bad | 0 running, 1 failed")
    assert lines[5].startswith("2 runs done in") and "(1 failed, 1 retried; 3 finished before)" in lines[5]
    assert len(lines) == 6


def _small(steps: int, seed: int = 0, **extra: object) -> dict[str, object]:
    out: dict[str, object] = {"train.total_steps": steps, "train.seed": seed, "agent.learning_starts": 50,
                              "agent.hidden_sizes": [16], "train.tensorboard": False, "train.progress": False,
                              "train.eval_interval": 100, "train.eval_episodes": 2, "train.final_eval_episodes": 3}  # fmt: skip
    out.update(extra)
    return out


def test_resume_at_an_evaluation_step_is_the_uninterrupted_run(tmp_path: Path) -> None:
    """What a retried Ray run does (resume from a periodic checkpoint sent to the driver) gives the
    files of the uninterrupted run, also when the checkpoint's step is an evaluation step; and the
    comparison would see a difference (another seed)."""
    snapshot = tmp_path / "snapshot"

    def keep_first(path: Path, step: int) -> None:
        if step == 200 and not snapshot.exists():
            shutil.copytree(path.parent, snapshot)

    cfg = load_experiment_config(CARTPOLE, _small(300, **{"train.checkpoint_interval": 100}))
    train(cfg, run_dir=tmp_path / "full", on_checkpoint=keep_first)
    assert (snapshot / "checkpoint.pt").is_file() and not (snapshot / "summary.json").exists()
    train(cfg, run_dir=snapshot, resume=snapshot / "checkpoint.pt")
    assert run_differences(tmp_path / "full", tmp_path / "full", snapshot, snapshot) == []
    eval_rows = [r for r in comparable_run(snapshot, snapshot)["metrics.csv"] if r[1] == "eval/mean_return"]
    assert [r[0] for r in eval_rows] == [0, 100, 200, 300]  # each evaluation once
    other = load_experiment_config(CARTPOLE, _small(300, seed=1, **{"train.checkpoint_interval": 100}))
    train(other, run_dir=tmp_path / "seed1")
    diffs = run_differences(tmp_path / "full", tmp_path / "full", tmp_path / "seed1", tmp_path / "seed1")
    assert "episodes.csv: differs" in diffs and "checkpoint.pt: differs" in diffs


def test_a_failing_sumo_run_closes_its_simulation(tmp_path: Path) -> None:
    """The runner closes its environment on an exception too: a process (a reused Ray worker) can
    run the next SUMO run; libsumo allows one simulation per process."""
    from sumo_bridge.sim_backend import libsumo_in_use

    bad = load_experiment_config(REPO / "config" / "ring.yaml", _small(60, **{"agent.network": "cnn"}))
    with pytest.raises(ValueError, match="cnn"):
        train(bad, run_dir=tmp_path / "bad")  # fails building the agent, after the env is up
    assert libsumo_in_use() is None


def test_progress_eta_counts_parallel_runs(caplog: pytest.LogCaptureFixture) -> None:
    """Two runs at a time, 100 s each: when the first ends, the other three need 100 s more (the
    running one ends now, then the last two side by side), not elapsed / done x remaining = 300 s."""
    specs = plan_runs("cfg.yaml", PAPER_METHODS[:1], [0, 1, 2, 3], "/out")
    now = [0.0]
    progress = SuiteProgress(total=4, stream=io.StringIO(), clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="der_ros.experiments.progress"):
        progress(RunEvent("started", specs[0]))
        progress(RunEvent("started", specs[1]))
        now[0] = 100.0
        progress(RunEvent("finished", specs[0], summary={"steps": 1}))
        assert progress.eta_s() == pytest.approx(100.0)
        progress(RunEvent("started", specs[2]))
        now[0] = 130.0
        progress(RunEvent("finished", specs[1], summary={"steps": 1}))  # mean 115 s: run 2 has 85 s left
        assert progress.eta_s() == pytest.approx(115.0)  # run 3 starts now on the free slot
        progress(RunEvent("started", specs[3]))
        progress(RunEvent("failed", specs[2], error=ValueError("bad")))  # a failure is no duration
        assert progress.eta_s() == pytest.approx(115.0)
        now[0] = 400.0  # overdue: the ETA does not go negative
        assert progress.eta_s() == 0.0
    lines = [r.getMessage() for r in caplog.records]
    assert lines[2].endswith("ETA 1:40")
