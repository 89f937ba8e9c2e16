"""The ROS-free supervisor of ``der graph``: start order, stop order, escalation, failure reports."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from der_ros.graph.supervisor import ChildFailed, ProcessSpec, Supervisor, reserve_domain_id, ros_environment

# A child that logs "ready", then waits; on SIGINT/SIGTERM it appends "<name> <signal>" to a journal
# and exits (or ignores the signal when told to).
CHILD = textwrap.dedent(
    """
    import signal, sys, time
    name, journal, ignore, exit_after = sys.argv[1], sys.argv[2], sys.argv[3].split(","), float(sys.argv[4])
    def handler(signum, frame):
        with open(journal, "a") as f:
            f.write(f"{name} {signal.Signals(signum).name}\\n")
        if signal.Signals(signum).name not in ignore:
            sys.exit(0)
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    print(f"{name} ready", flush=True)
    t0 = time.monotonic()
    while True:
        time.sleep(0.02)
        if exit_after >= 0 and time.monotonic() - t0 > exit_after:
            print(f"{name} exits on its own", flush=True)
            sys.exit(int(exit_after * 10) % 7)
    """
)


def child(tmp_path: Path, name: str, *, ignore: str = "", exit_after: float = -1, finishes: bool = False) -> ProcessSpec:
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    return ProcessSpec(
        name=name,
        argv=[sys.executable, str(script), name, str(tmp_path / "journal"), ignore, str(exit_after)],
        ready_pattern=rf"{name} ready",
        ready_timeout=20,
        finishes_run=finishes,
    )


def journal(tmp_path: Path) -> list[str]:
    path = tmp_path / "journal"
    return path.read_text().splitlines() if path.exists() else []


def test_stops_in_order_with_sigint_and_writes_pids(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path / "run", stop_order=["bridge", "agent", "recorder"], grace_int=5, grace_term=5)
    sup.start_all([child(tmp_path, n) for n in ("recorder", "agent", "bridge")])
    pids = json.loads((tmp_path / "run" / "pids.json").read_text())
    assert set(pids) == {"recorder", "agent", "bridge"} and pids["agent"] == sup.procs["agent"].pid
    outcome = sup.supervise(until=lambda: True)
    assert outcome.ok and outcome.reason == "stopped"
    assert journal(tmp_path) == ["bridge SIGINT", "agent SIGINT", "recorder SIGINT"]
    assert outcome.exit_codes == {"recorder": 0, "agent": 0, "bridge": 0}
    assert "ready" in (tmp_path / "run" / "logs" / "agent.log").read_text()


def test_escalates_to_sigterm_then_sigkill(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path / "run", grace_int=0.5, grace_term=0.5)
    sup.start_all([child(tmp_path, "stubborn", ignore="SIGINT,SIGTERM"), child(tmp_path, "polite", ignore="SIGINT")])
    t0 = time.monotonic()
    codes = sup.stop_all()
    assert time.monotonic() - t0 < 10
    assert codes["stubborn"] == -signal.SIGKILL
    assert codes["polite"] == 0
    # reverse start order when no stop order is given
    assert journal(tmp_path) == ["polite SIGINT", "polite SIGTERM", "stubborn SIGINT", "stubborn SIGTERM"]


def test_unexpected_death_stops_the_others_and_names_the_dead(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path / "run", stop_order=["bridge", "agent", "recorder"], grace_int=5)
    sup.start_all([child(tmp_path, "recorder"), child(tmp_path, "agent", exit_after=0.3), child(tmp_path, "bridge")])
    outcome = sup.supervise(poll_interval=0.05)
    assert not outcome.ok and outcome.failed == "agent"
    assert outcome.reason == "agent died (exit 3)"
    assert "agent exits on its own" in outcome.describe()
    assert journal(tmp_path) == ["bridge SIGINT", "recorder SIGINT"]
    assert outcome.exit_codes["recorder"] == 0


def test_a_finishing_source_ends_the_run_normally(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path / "run", stop_order=["bridge", "agent", "recorder"])
    # exit_after=0.7 -> exit code int(7) % 7 == 0
    sup.start_all([child(tmp_path, "recorder"), child(tmp_path, "agent"), child(tmp_path, "bridge", exit_after=0.7,
                                                                                    finishes=True)])
    outcome = sup.supervise(poll_interval=0.05)
    assert outcome.ok and outcome.reason == "finished", outcome.describe()
    assert journal(tmp_path) == ["agent SIGINT", "recorder SIGINT"]


def test_child_dying_during_start_up_is_reported(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path / "run")
    bad = ProcessSpec("broken", [sys.executable, "-c", "import sys; print('boom: bad parameter'); sys.exit(2)"],
                      ready_pattern="never")
    sup.start(bad)
    with pytest.raises(ChildFailed, match="broken exited with 2") as info:
        sup.wait_ready("broken")
    assert "boom: bad parameter" in info.value.tail
    sup.stop_all()


def test_domain_ids_and_environment() -> None:
    a = reserve_domain_id()
    b = reserve_domain_id()
    try:
        assert 1 <= a.domain_id <= 101 and 1 <= b.domain_id <= 101 and a.domain_id != b.domain_id
    finally:
        a.release()
        b.release()
    assert reserve_domain_id(42).domain_id == 42
    with pytest.raises(ValueError, match="domain id"):
        reserve_domain_id(0)
    env = ros_environment(7, {"PATH": "/bin", "ROS_LOCALHOST_ONLY": "1"})
    assert env["ROS_DOMAIN_ID"] == "7" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert "ROS_LOCALHOST_ONLY" not in env and env["PATH"] == "/bin"


@pytest.mark.parametrize(
    ("value", "expected"),
    [("self", "True"), ("1", "False"), (None, "True"), ("not-a-pid", "True")],
    ids=["supervisor-alive", "supervisor-gone", "no-supervisor", "garbage"],
)
def test_stop_with_supervisor_reports_a_supervisor_that_is_already_gone(value: str | None, expected: str) -> None:
    """A child whose parent is not the pid it was given (the supervisor died before the child
    could ask for PR_SET_PDEATHSIG) must be told to stop at once."""
    from der_ros.nodes.orphans import SUPERVISOR_PID_ENV

    env = {k: v for k, v in os.environ.items() if k != SUPERVISOR_PID_ENV}
    if value is not None:
        env[SUPERVISOR_PID_ENV] = str(os.getpid()) if value == "self" else value
    code = "from der_ros.nodes.orphans import stop_with_supervisor as s; print(s())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == (expected if sys.platform.startswith("linux") else "True")
