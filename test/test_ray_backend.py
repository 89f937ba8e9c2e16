"""``--backend ray`` on a Ray instance on this machine (127.0.0.1, no dashboard).

* SUMO runs twice in one Ray worker process (after a run that failed with its simulation open);
* a tiny sweep gives the same per-run files as the local backend (run_compare's definition);
* a worker killed mid-run: the sweep completes, the run is retried from the checkpoint that
  reached the driver and equals an uninterrupted run of the same seed.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import ray
from ray_helpers import CARTPOLE, LOOPBACK, REPO, ray_listening_addresses, ray_test_env, small_cartpole

from der_ros.experiments.backends import LocalBackend, RayBackend, RunEvent, SuiteRunError, run_specs
from der_ros.experiments.backends.ray_cluster import loopback_ray
from der_ros.experiments.run_compare import run_differences
from der_ros.experiments.suite import methods_by_name, plan_runs

pytestmark = pytest.mark.slow


@pytest.fixture
def ray_one_cpu(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A Ray instance with one CPU: consecutive tasks run in the same worker process."""
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
    backend = RayBackend()
    # a run that fails after its simulation is up (the network cannot take the observation)
    bad = plan_runs(ring, dqn, [0], tmp_path, small | {"agent.network": "cnn"}, group="bad")
    with pytest.raises(SuiteRunError, match="cnn"):
        run_specs(bad, backend=backend, on_event=events.append)
    good = plan_runs(ring, dqn, [0, 1], tmp_path, small, group="good")
    summaries = run_specs(good, backend=backend, on_event=events.append)
    assert sorted(s["steps"] for s in summaries) == [60, 60]
    started = [e for e in events if e.kind == "started"]
    assert len(started) == 3 and len({e.where["pid"] for e in started}) == 1  # one worker process, three runs
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


def test_tiny_sweep_gives_the_local_backends_files(tmp_path: Path, ray_two_cpus: None) -> None:
    methods = methods_by_name(["dqn", "der0.9"])
    small = small_cartpole(300, **{"train.checkpoint_interval": 150})
    local = plan_runs(CARTPOLE, methods, [0, 1], tmp_path / "local", small)
    remote = plan_runs(CARTPOLE, methods, [0, 1], tmp_path / "ray", small)
    run_specs(local, backend=LocalBackend(2))
    addresses: set[str] = set()
    events: list[RunEvent] = []

    def watch(event: RunEvent) -> None:
        events.append(event)
        if event.kind == "started":
            addresses.update(ray_listening_addresses())

    run_specs(remote, backend=RayBackend(), on_event=watch)
    assert addresses and addresses <= LOOPBACK, addresses  # Ray's servers listen on loopback only
    for a, b in zip(local, remote):
        assert run_differences(a.run_dir, tmp_path / "local", b.run_dir, tmp_path / "ray") == []
        names = sorted(p.name for p in Path(b.run_dir).iterdir())
        assert names == sorted(p.name for p in Path(a.run_dir).iterdir())
    # the comparison is not vacuous: two seeds differ
    assert run_differences(remote[0].run_dir, tmp_path, remote[1].run_dir, tmp_path)
    # files came from the workers' own folders, which are gone
    workdirs = {e.where["workdir"] for e in events if e.kind == "finished"}
    assert len(workdirs) == 4 and not any(Path(w).exists() for w in workdirs)
    assert all(not w.startswith(str(tmp_path)) for w in workdirs)
    # a rerun skips the finished runs: no event, no task
    again: list[RunEvent] = []
    assert run_specs(remote, backend=RayBackend(), on_event=again.append) == [] and again == []


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
    assert len(retry) == 1 and retry[0].spec.seed == 0 and retry[0].step == 250  # resumed, not restarted
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
