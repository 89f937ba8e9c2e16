"""Harness for node tests: real node processes plus an rclpy node inside the test process.

Isolation: every test gets its own ``ROS_DOMAIN_ID`` (1..101, reserved with a lock file so that
concurrent pytest runs on the same machine never share one), discovery is limited to this host
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), node output goes to files that are printed on
failure (pytest shows a failing test's captured teardown output), and every process is stopped
(SIGINT, then SIGKILL after a grace period) and reaped in teardown.

Usage (fixtures ``ros_graph`` / ``ros_domain`` are exported for ``from ros_harness import *``)::

    def test_x(ros_graph):
        bridge = ros_graph.start_node("der_ros.nodes.bridge_node", params={"max_steps": 50})
        states = ros_graph.probe.collect("state", PointCloud2)
        wait_for(lambda: len(states) >= 3, timeout=20, what="three states", procs=[bridge])

Generic API: :func:`start_node`, :class:`NodeProcess`, :class:`ProbeNode`, :func:`wait_for`,
:func:`reserve_domain_id`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml

from der_ros.graph.supervisor import ManagedProcess, ProcessSpec, reserve_domain_id, ros_environment
from der_ros.nodes.spin import BackgroundNode

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

__all__ = [
    "NodeProcess",
    "ProbeNode",
    "RosGraph",
    "reserve_domain_id",
    "start_node",
    "wait_for",
    "ros_domain",
    "ros_graph",
]

REPO = Path(__file__).resolve().parents[1]


# -- waiting ------------------------------------------------------------------------------------
def wait_for(
    predicate: Callable[[], Any],
    timeout: float,
    what: str = "condition",
    interval: float = 0.01,
    procs: Iterable[NodeProcess] = (),
) -> Any:
    """Poll ``predicate`` until it returns a truthy value (returned) or fail the test.

    Fails early, with the process output, if one of ``procs`` exits meanwhile.
    """
    deadline = time.monotonic() + timeout
    procs = list(procs)
    while True:
        value = predicate()
        if value:
            return value
        for p in procs:
            if p.poll() is not None:
                pytest.fail(f"{p.name} exited with {p.poll()} while waiting for {what}:\n{p.output()[-4000:]}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


# -- node processes -----------------------------------------------------------------------------
class NodeProcess(ManagedProcess):
    """A node running in its own process (own session, so signals reach only it), run from the repo root."""

    def __init__(self, name: str, argv: list[str], env: Mapping[str, str], log_path: Path) -> None:
        super().__init__(ProcessSpec(name, argv, env), log_path, cwd=REPO)
        self.argv = argv

    def signal(self, sig: int) -> None:
        self.send(sig)

    def wait(self, timeout: float) -> int:
        """Wait for exit; returns the exit code (raises subprocess.TimeoutExpired)."""
        return self.proc.wait(timeout=timeout)

    def stop(self, grace: float = 10.0) -> int:
        """SIGINT, then SIGKILL (whole session) after ``grace`` seconds; reaps; returns the exit code."""
        if self.proc.poll() is None:
            self.signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.proc.wait(timeout=10)
        self.close()
        return self.proc.returncode


def _param_arg(name: str, value: Any) -> str:
    text = yaml.safe_dump(value, default_flow_style=True).strip()
    if text.endswith("\n..."):
        text = text[: -len("\n...")]
    text = text.removesuffix("...").strip()
    return f"{name}:={text}"


def start_node(
    executable_module: str,
    params_file: str | Path | None = None,
    params: Mapping[str, Any] | None = None,
    name: str | None = None,
    *,
    domain_id: int,
    log_dir: Path,
    env: Mapping[str, str] | None = None,
    extra_ros_args: Iterable[str] = (),
) -> NodeProcess:
    """Start ``python -m executable_module --ros-args ...`` in the given domain.

    ``params`` become ``-p name:=value`` (values YAML-encoded, so lists and floats keep their
    type); ``name`` remaps the node name (``-r __node:=name``) and names the log file.
    """
    label = name or executable_module.rsplit(".", 1)[-1]
    argv = [sys.executable, "-m", executable_module, "--ros-args"]
    if name:
        argv += ["-r", f"__node:={name}"]
    if params_file is not None:
        argv += ["--params-file", str(params_file)]
    for k, v in (params or {}).items():
        argv += ["-p", _param_arg(k, v)]
    argv += list(extra_ros_args)
    full_env = ros_environment(domain_id)
    full_env.update(env or {})
    log_path = log_dir / f"{label}-{int(time.time() * 1000) % 10_000_000}.log"
    return NodeProcess(label, argv, full_env, log_path)


# -- in-test rclpy node -------------------------------------------------------------------------
class ProbeNode(BackgroundNode):
    """An rclpy node in the test process, spinning in a background thread, in its own Context."""

    def __init__(self, domain_id: int, name: str = "test_probe") -> None:
        super().__init__(name, domain_id, spin_timeout=0.05, thread_name="probe-spin")
        self.lock = threading.Lock()
        self._clients: dict[tuple[type, str], Any] = {}
        self.start()

    def collect(self, topic: str, msg_type: type, qos: Any = 100, with_info: bool = False) -> list[Any]:
        """Subscribe; returns the list the messages (or (msg, info, t_recv) tuples) are appended to."""
        out: list[Any] = []
        if with_info:
            self.node.create_subscription(msg_type, topic, lambda m, i: out.append((m, i, time.monotonic())), qos)
        else:
            self.node.create_subscription(msg_type, topic, out.append, qos)
        return out

    def publisher(self, topic: str, msg_type: type, qos: Any = 10) -> Any:
        return self.node.create_publisher(msg_type, topic, qos)

    def call(self, srv_type: type, name: str, request: Any, timeout: float = 10.0, attempt: float = 2.5) -> Any:
        """Call a service and wait for the response (fails the test on timeout).

        One client per service, kept: a new client's reply reader may not be matched yet by the
        server's reply writer when the first request arrives (``wait_for_service`` sees the server,
        not that), and Fast DDS then drops the response after a short wait; under load that is what
        a fresh client per call kept hitting. So a request without a response after ``attempt``
        seconds is sent again until ``timeout``: only for requests that may be repeated (every
        service here: set/get parameters, pause, save a checkpoint).
        """
        key = (srv_type, name)
        client = self._clients.get(key)
        if client is None:
            client = self._clients[key] = self.node.create_client(srv_type, name)
        deadline = time.monotonic() + timeout
        if not client.wait_for_service(timeout_sec=timeout):
            pytest.fail(f"service {name} not available after {timeout} s")
        sent = 0
        while True:
            future = client.call_async(request)
            sent += 1
            until = min(deadline, time.monotonic() + attempt)
            while not future.done() and time.monotonic() < until:
                time.sleep(0.01)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
            if time.monotonic() >= deadline:
                pytest.fail(f"no response of {name} after {timeout} s ({sent} requests)")

    def set_parameters(self, node_name: str, values: Mapping[str, Any], timeout: float = 10.0) -> list[Any]:
        """Call ``/<node>/set_parameters``; returns the list of SetParametersResult."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        return list(self.call(SetParameters, f"/{node_name}/set_parameters", req, timeout).results)

    def get_parameters(self, node_name: str, names: list[str], timeout: float = 10.0) -> dict[str, Any]:
        """Call ``/<node>/get_parameters``; returns name -> Python value."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        res = self.call(GetParameters, f"/{node_name}/get_parameters", GetParameters.Request(names=names), timeout)
        return {n: parameter_value_to_python(v) for n, v in zip(names, res.values)}


class RosGraph:
    """Per-test bundle: a domain id, started node processes, a probe node; cleaned up in teardown."""

    def __init__(self, domain_id: int, log_dir: Path) -> None:
        self.domain_id = domain_id
        self.log_dir = log_dir
        self.procs: list[NodeProcess] = []
        self._probe: ProbeNode | None = None

    @property
    def probe(self) -> ProbeNode:
        if self._probe is None:
            self._probe = ProbeNode(self.domain_id)
        return self._probe

    def start_node(
        self,
        executable_module: str,
        params_file: str | Path | None = None,
        params: Mapping[str, Any] | None = None,
        name: str | None = None,
        **kwargs: Any,
    ) -> NodeProcess:
        p = start_node(
            executable_module, params_file, params, name, domain_id=self.domain_id, log_dir=self.log_dir, **kwargs
        )
        self.procs.append(p)
        return p

    def close(self) -> None:
        for p in self.procs:
            code = p.stop()
            print(f"===== {p.name} (pid {p.pid}, exit {code}) {' '.join(p.argv[2:])}\n{p.output()[-20000:]}")
        if self._probe is not None:
            self._probe.close()


@pytest.fixture
def ros_domain() -> Any:
    """A reserved ROS domain id for this test."""
    lease = reserve_domain_id()
    try:
        yield lease.domain_id
    finally:
        lease.release()


@pytest.fixture
def ros_graph(ros_domain: int, tmp_path: Path) -> Any:
    """A :class:`RosGraph` in this test's domain; all processes stopped and reaped afterwards."""
    graph = RosGraph(ros_domain, tmp_path)
    try:
        yield graph
    finally:
        graph.close()
