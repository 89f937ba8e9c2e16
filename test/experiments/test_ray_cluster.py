"""A simulated two-node Ray cluster on this machine, started the way docs/cluster.md says (``ray start``).

Head and second node each bind to 127.0.0.1 with ports of their own; the second node has a
custom resource (``node2``) and its own temporary folder (``TMPDIR``), where its workers train.
The sweep runs tasks on both nodes; a run pinned to ``node2`` with ``--resources-per-run``
arrives in the driver's ``--out`` although its worker wrote only into its own temporary folder,
which is gone afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import ray
from ray_helpers import CARTPOLE, LOOPBACK, free_port, ray_listening_addresses, ray_test_env, small_cartpole

from der_ros.experiments.backends.dispatch import RayBackend, RunEvent, run_specs
from der_ros.experiments.backends.ray_cluster import loopback_ray
from der_ros.experiments.suite import methods_by_name, plan_runs

pytestmark = pytest.mark.slow

RAY = str(Path(sys.executable).with_name("ray"))
#: `ray start` for a second node on 127.0.0.1. Ray's CLI refuses a second node in single-machine
#: mode (RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0, what keeps a node on the loopback address), and
#: outside it rewrites 127.0.0.1 into the machine's network address; this lifts only the refusal.
SECOND_NODE = """
import sys
import ray._private.ray_constants as constants
import ray._private.services as services
from ray.scripts.scripts import main
constants.ENABLE_RAY_CLUSTER = True
services.get_node_ip_address = lambda address=None: "127.0.0.1"
sys.argv = ["ray", *sys.argv[1:]]
main()
"""


def _ports(n: int) -> list[int]:
    out: set[int] = set()
    while len(out) < n:
        out.add(free_port())
    return sorted(out)


def _node_ports() -> list[str]:
    names = ("node-manager-port", "object-manager-port", "dashboard-agent-listen-port", "dashboard-agent-grpc-port",
             "runtime-env-agent-port", "metrics-export-port")  # fmt: skip
    return [f"--{n}={p}" for n, p in zip(names, _ports(len(names)))]


def _worker_range(offset: int) -> list[str]:
    base = 20000 + (os.getpid() % 400) * 100 + offset  # a block of this test's own
    return [f"--min-worker-port={base}", f"--max-worker-port={base + 40}"]


def _wait_port(port: int, proc: subprocess.Popen[bytes], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"ray start exited with {proc.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.5)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout} s")


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    """SIGTERM each node's process group (a node drains, then stops its processes), SIGKILL after 10 s."""
    for p in procs:
        try:
            os.killpg(p.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=20)
        try:  # what the node started in its group (raylet, agents, workers) goes too
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.fixture
def two_nodes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, object]]:
    env = ray_test_env(monkeypatch)
    head_port = free_port()
    ray_tmp = Path(f"/tmp/der-ray-{os.getpid()}-{head_port}")  # short: Ray's socket paths have a length limit
    node2_tmp = tmp_path / "node2_tmp"
    node2_tmp.mkdir()
    procs: list[subprocess.Popen[bytes]] = []
    logs = [open(tmp_path / "head.log", "wb"), open(tmp_path / "node2.log", "wb")]
    try:
        head = [RAY, "start", "--head", f"--port={head_port}", f"--ray-client-server-port={free_port()}",
                "--num-cpus=1", "--include-dashboard=false", f"--temp-dir={ray_tmp}", "--disable-usage-stats",
                "--block", *_node_ports(), *_worker_range(0)]  # fmt: skip
        procs.append(subprocess.Popen(head, env=env, stdout=logs[0], stderr=subprocess.STDOUT, start_new_session=True))
        _wait_port(head_port, procs[0])
        second = [sys.executable, "-c", SECOND_NODE, "start", f"--address=127.0.0.1:{head_port}", "--num-cpus=1",
                  '--resources={"node2": 1}', "--disable-usage-stats", "--block", *_node_ports(),
                  *_worker_range(50)]  # fmt: skip
        procs.append(subprocess.Popen(second, env=env | {"TMPDIR": str(node2_tmp)}, stdout=logs[1],
                                      stderr=subprocess.STDOUT, start_new_session=True))  # fmt: skip
        with loopback_ray():  # the driver resolves 127.0.0.1 as 127.0.0.1
            ray.init(address=f"127.0.0.1:{head_port}", logging_level="WARNING")
            deadline = time.monotonic() + 120
            while sum(1 for n in ray.nodes() if n["Alive"]) < 2:
                assert time.monotonic() < deadline, "the second node did not join"
                assert procs[1].poll() is None, (tmp_path / "node2.log").read_text()[-2000:]
                time.sleep(0.5)
            nodes = {n["NodeID"]: n for n in ray.nodes() if n["Alive"]}
            node2 = next(i for i, n in nodes.items() if n["Resources"].get("node2"))
            head_id = next(i for i in nodes if i != node2)
            yield {"head": head_id, "node2": node2, "node2_tmp": node2_tmp, "address": f"127.0.0.1:{head_port}"}
    finally:
        ray.shutdown()
        _stop(procs)
        for f in logs:
            f.close()
        subprocess.run(["rm", "-rf", str(ray_tmp)], check=False)


def test_two_node_cluster_runs_on_both_and_ships_artifacts(tmp_path: Path, two_nodes: dict[str, object]) -> None:
    assert ray_listening_addresses() <= LOOPBACK
    methods = methods_by_name(["dqn"])
    small = small_cartpole(200, **{"train.eval_interval": 0, "train.final_eval_episodes": 2})
    events: list[RunEvent] = []
    out = tmp_path / "out"
    # two runs, one CPU per node: one on each
    run_specs(plan_runs(CARTPOLE, methods, [0, 1], out, small), backend=RayBackend(), on_event=events.append)
    # one run pinned to the second node by its custom resource
    pinned = plan_runs(CARTPOLE, methods, [2], out, small)
    run_specs(pinned, backend=RayBackend(resources={"node2": 1}), on_event=events.append)
    finished = [e for e in events if e.kind == "finished"]
    assert len(finished) == 3
    assert {e.where["node"] for e in finished[:2]} == {two_nodes["head"], two_nodes["node2"]}
    last = finished[2]
    assert last.spec.seed == 2 and last.where["node"] == two_nodes["node2"]
    # the second node's worker trained in its own temporary folder, now removed ...
    assert last.where["workdir"].startswith(str(two_nodes["node2_tmp"]))
    assert not Path(last.where["workdir"]).exists() and not list(Path(two_nodes["node2_tmp"]).glob("der-ray-run-*"))
    # ... and the files arrived in the driver's --out, naming the driver's folder
    run = Path(pinned[0].run_dir)
    for name in ("summary.json", "metrics.csv", "episodes.csv", "config.yaml", "command.txt", "evaluation.json",
                 "checkpoint.pt"):  # fmt: skip
        assert (run / name).is_file(), name
    summary = json.loads((run / "summary.json").read_text())
    assert summary["run_dir"] == str(run) and summary["checkpoint"] == str(run / "checkpoint.pt")
    assert summary["steps"] == 200
