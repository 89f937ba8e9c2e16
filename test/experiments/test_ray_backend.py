"""``--backend ray`` on a Ray instance on this machine (127.0.0.1, no dashboard).

* SUMO runs twice in one Ray worker process (after a run that failed with its simulation open);
* a tiny sweep gives the same per-run files as the local backend (run_compare's definition);
* a worker killed mid-run: the sweep completes, the run is retried from the checkpoint that
  reached the driver and equals an uninterrupted run of the same seed.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import ray
from ray_helpers import CARTPOLE, LOOPBACK, REPO, ray_listening_addresses, ray_test_env, small_cartpole

from der_ros import cli
from der_ros.experiments import sweep
from der_ros.experiments.backends import dispatch as backends
from der_ros.experiments.backends.dispatch import LocalBackend, RayBackend, RunEvent, SuiteRunError, run_specs
from der_ros.experiments.backends.ray_cluster import loopback_ray
from der_ros.experiments.run_compare import run_differences
from der_ros.experiments.suite import methods_by_name, plan_runs
from der_ros.experiments.sweep import grid_methods, parse_grid
from der_ros.train.eval_seeds import TUNING_EVAL_SEED_BASE

pytestmark = pytest.mark.slow


@pytest.fixture
def ray_one_cpu(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A Ray instance with one CPU: tasks submitted one after the other run in the same worker
    process (queued tasks would not: Ray starts spare workers for a backlog and may use those)."""
    ray_test_env(monkeypatch)
    tmp = tempfile.mkdtemp(prefix="der-ray-", dir="/tmp")
    try:
        with loopback_ray():
            ray.init(address="local", num_cpus=1, include_dashboard=False, _temp_dir=tmp,
                     logging_level=logging.WARNING)  # fmt: skip
            yield
    finally:
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)


def test_sumo_runs_twice_in_one_ray_worker(tmp_path: Path, ray_one_cpu: None) -> None:
    small = {"train.total_steps": 60, "agent.learning_starts": 30, "agent.hidden_sizes": [16],
             "train.tensorboard": False, "train.eval_interval": 30, "train.eval_episodes": 1,
             "train.final_eval_episodes": 1}  # fmt: skip
    dqn = methods_by_name(["dqn"])
    ring = REPO / "config" / "ring.yaml"
    events: list[RunEvent] = []
    # first a run that fails after its simulation is up (the network cannot take the observation),
    # then two that work, one at a time
    bad = plan_runs(ring, dqn, [0], tmp_path, small | {"agent.network": "cnn"}, group="bad")
    with pytest.raises(SuiteRunError, match="cnn"):
        run_specs(bad, backend=RayBackend(), on_event=events.append)
    good = plan_runs(ring, dqn, [0, 1], tmp_path, small, group="good")
    for spec in good:
        assert [s["steps"] for s in run_specs([spec], backend=RayBackend(), on_event=events.append)] == [60]
    started = [e for e in events if e.kind == "started"]
    assert len(started) == 3 and len({e.where["pid"] for e in started}) == 1  # one worker process, three runs
    assert started[0].spec.group == "bad"  # the failed run came first: its simulation did not stay open
    assert not [e for e in events if e.kind == "retry"]  # the run's own error is not retried
    for spec in good:
        run = Path(spec.run_dir)
        assert (run / "evaluation.json").is_file() and (run / "checkpoint.pt").is_file()
        assert (run / "evaluations.csv").read_text().count("\n") == 4  # header + steps 0, 30, 60 (final)
    assert ray.is_initialized()  # the caller's Ray is left running


@pytest.fixture(scope="module")
def ray_two_cpus() -> Iterator[None]:
    """The local Ray instance of the tests below: 2 CPUs, no dashboard, every server on 127.0.0.1."""
    with pytest.MonkeyPatch.context() as mp:
        ray_test_env(mp)
        tmp = tempfile.mkdtemp(prefix="der-ray-", dir="/tmp")
        try:
            with loopback_ray():
                ray.init(address="local", num_cpus=2, include_dashboard=False, _temp_dir=tmp,
                         logging_level=logging.WARNING)  # fmt: skip
                yield
        finally:
            ray.shutdown()
            shutil.rmtree(tmp, ignore_errors=True)


def test_tiny_sweep_gives_the_local_backends_files(tmp_path: Path, ray_two_cpus: None,
                                                  capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """`der sweep` with 2 methods x 2 seeds on both backends: the same run files and the same table."""
    argv = ["sweep", str(CARTPOLE), "--grid", "replay.kind=uniform,der", "--seeds", "2", "--first-seed", "0"]
    for k, v in small_cartpole(300, **{"train.checkpoint_interval": 150, "replay.lam": 0.9}).items():
        argv += ["--set", f"{k}={json.dumps(v)}"]
    assert cli.main([*argv, "--out", str(tmp_path / "local"), "--jobs", "2"]) == 0
    addresses: set[str] = set()
    events: list[RunEvent] = []

    def watch(event: RunEvent) -> None:
        events.append(event)
        if event.kind == "started":
            addresses.update(ray_listening_addresses())

    with _watching(watch):
        assert cli.main([*argv, "--out", str(tmp_path / "ray"), "--backend", "ray"]) == 0
    capsys.readouterr()
    assert addresses and addresses <= LOOPBACK, addresses  # Ray's servers listen on loopback only
    local_runs = sorted((tmp_path / "local").glob("*/seed*"))
    assert len(local_runs) == 4
    for a in local_runs:
        b = tmp_path / "ray" / a.relative_to(tmp_path / "local")
        assert run_differences(a, tmp_path / "local", b, tmp_path / "ray") == []
        assert sorted(p.name for p in b.iterdir()) == sorted(p.name for p in a.iterdir())
    # the comparison is not vacuous: two seeds differ
    assert run_differences(local_runs[0], tmp_path, local_runs[1], tmp_path)
    # the table written at the end is the same
    table = {n: (tmp_path / n / "sweep.md").read_text().split("## Runs")[0] for n in ("local", "ray")}
    assert table["local"] == table["ray"] and "`kind=der`" in table["local"]
    points = {n: {k: {f: v for f, v in point.items() if f != "wall_time_s"}  # the one timing per run
                  for k, point in json.loads((tmp_path / n / "sweep.json").read_text())["points"].items()}
              for n in ("local", "ray")}  # fmt: skip
    assert points["local"] == points["ray"] and len(points["ray"]["kind=der"]["eval_return"]) == 2
    # files came from the workers' own folders, which are gone
    workdirs = {e.where["workdir"] for e in events if e.kind == "finished"}
    assert len(workdirs) == 4 and not any(Path(w).exists() for w in workdirs)
    assert all(not w.startswith(str(tmp_path)) for w in workdirs)
    # a rerun of the same sweep (its tuning evaluation seeds included) skips the finished runs: no event, no task
    again: list[RunEvent] = []
    same = {"train.checkpoint_interval": 150, "replay.lam": 0.9, "train.eval_seed_base": TUNING_EVAL_SEED_BASE}
    specs = plan_runs(CARTPOLE, grid_methods(parse_grid(["replay.kind=uniform,der"])), [0, 1], tmp_path / "ray",
                      small_cartpole(300, **same))  # fmt: skip
    assert run_specs(specs, backend=RayBackend(), on_event=again.append) == [] and again == []


@contextmanager
def _watching(sink: Callable[[RunEvent], None]) -> Iterator[None]:
    """Route the events of runs started through the CLI to ``sink`` (the CLI takes no hook)."""
    original = backends.run_specs

    def with_hook(specs: Any, jobs: Any = None, backend: Any = None, on_event: Any = None) -> Any:
        return original(specs, jobs, backend, on_event=sink)

    with pytest.MonkeyPatch.context() as mp:
        for module in (backends, sweep):
            mp.setattr(module, "run_specs", with_hook)
        yield


def test_killed_worker_is_retried_from_its_checkpoint(tmp_path: Path, ray_two_cpus: None) -> None:
    methods = methods_by_name(["der0.9"])
    small = small_cartpole(2000, **{"train.checkpoint_interval": 250, "train.eval_interval": 250})
    specs = plan_runs(CARTPOLE, methods, [0, 1], tmp_path / "ray", small)
    killed: list[tuple[int, int]] = []
    events: list[RunEvent] = []

    def kill_seed0_once(event: RunEvent) -> None:
        events.append(event)
        if event.kind == "checkpoint" and event.spec.seed == 0 and not killed:
            killed.append((event.where["pid"], int(event.step or 0)))
            os.kill(event.where["pid"], signal.SIGKILL)

    summaries = run_specs(specs, backend=RayBackend(max_retries=1), on_event=kill_seed0_once)
    assert sorted(s["steps"] for s in summaries) == [2000, 2000]
    assert killed and killed[0][1] == 250
    retry = [e for e in events if e.kind == "retry"]
    # resumed, not restarted: from the last checkpoint that reached the driver before the worker died
    # (the worker runs on while the driver handles the first one, so a later one may have arrived too)
    reached = [int(e.step or 0) for e in events if e.kind == "checkpoint" and e.spec.seed == 0 and e.attempt == 0]
    assert len(retry) == 1 and retry[0].spec.seed == 0 and retry[0].step == max(reached) >= 250, (retry, reached)
    assert "WorkerCrashedError" in str(retry[0].error)
    restarted = [e for e in events if e.kind == "started" and e.spec.seed == 0]
    assert [e.attempt for e in restarted] == [0, 1] and restarted[1].where["pid"] != killed[0][0]
    assert not Path(restarted[0].where["workdir"]).exists()  # the killed worker's folder was cleaned up
    # the retried run equals an uninterrupted run of the same seed
    reference = plan_runs(CARTPOLE, methods, [0], tmp_path / "local", small)
    run_specs(reference, backend=LocalBackend(1))
    assert run_differences(reference[0].run_dir, tmp_path / "local", specs[0].run_dir, tmp_path / "ray") == []


def test_a_run_lost_more_often_than_allowed_is_reported(tmp_path: Path, ray_two_cpus: None) -> None:
    methods = methods_by_name(["dqn"])
    specs = plan_runs(CARTPOLE, methods, [0], tmp_path, small_cartpole(3000, **{"train.eval_interval": 0}))

    workdirs: list[str] = []

    def kill_every_attempt(event: RunEvent) -> None:
        if event.kind == "started":
            workdirs.append(event.where["workdir"])
            os.kill(event.where["pid"], signal.SIGKILL)

    try:
        with pytest.raises(SuiteRunError) as err:
            run_specs(specs, backend=RayBackend(max_retries=1), on_event=kill_every_attempt)
    finally:  # the last killed worker's folder waits for the next run on the node: none comes
        for w in workdirs:
            shutil.rmtree(w, ignore_errors=True)
    assert len(workdirs) == 2
    text = str(err.value)
    assert "1 run(s) failed" in text and "dqn/seed0" in text
    assert "WorkerCrashedError" in text and "worker lost 2 times; --max-retries 1" in text
    assert not (tmp_path / "dqn" / "seed0" / "summary.json").exists()


def test_ctrl_c_on_the_driver_saves_checkpoints_and_a_rerun_finishes(tmp_path: Path) -> None:
    """Ctrl-C on `der sweep --backend ray` (SIGINT to its process group, as a terminal sends it):
    the runs in progress stop after a step, their checkpoints reach --out, the command exits 130;
    the same command again resumes them and finishes."""
    out, log = tmp_path / "out", tmp_path / "driver.log"
    cmd = [sys.executable, "-m", "der_ros.cli", "sweep", str(CARTPOLE), "--grid", "replay.kind=uniform,der",
           "--seeds", "1", "--first-seed", "0", "--out", str(out), "--backend", "ray", "--jobs", "2"]  # fmt: skip
    total = 20_000
    extra = {"train.eval_interval": 0, "train.final_eval_episodes": 2, "train.checkpoint_interval": 500}
    for k, v in small_cartpole(total, **extra).items():
        cmd += ["--set", f"{k}={json.dumps(v)}"]
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
        try:
            deadline = time.monotonic() + 180
            # both runs are in their training loops once each one's first checkpoint (step 500) has
            # reached --out; then Ctrl-C at once (a fixed sleep let a fast machine finish a run first)
            while len(list(out.glob("kind=*/seed0/checkpoint.pt"))) < 2:
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
                time.sleep(0.05)
            os.killpg(proc.pid, signal.SIGINT)
            assert proc.wait(timeout=120) == 130, log.read_text()[-3000:]
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    text = log.read_text()
    assert "runs in progress save a checkpoint" in text and "Traceback" not in text
    runs = sorted(out.glob("kind=*/seed0"))
    assert len(runs) == 2
    stopped = {}
    for run in runs:
        summary = json.loads((run / "summary.json").read_text())
        assert summary["interrupted"] and 0 < summary["steps"] < total, summary
        assert (run / "checkpoint.pt").is_file()
        stopped[run.name] = summary["steps"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    for run in runs:
        summary = json.loads((run / "summary.json").read_text())
        assert summary["steps"] == total and not summary["interrupted"]
        steps = [int(line.split(",")[1]) for line in (run / "episodes.csv").read_text().splitlines()[1:]]
        assert steps == sorted(steps) and steps[-1] > stopped[run.name]  # continued, not restarted
    assert (out / "sweep.md").is_file()
