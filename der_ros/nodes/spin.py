"""Process life cycle shared by the node executables: init, spin until done or signalled, clean up.

rclpy's own SIGINT/SIGTERM handlers shut the context down from inside the signal handler, after
which a node can no longer publish or save through ROS. The node executables instead install
handlers that only set a flag; the spin loop then returns, the node's ``on_shutdown()`` runs
with ROS still up (final checkpoint, summary log, last diagnostics), and the process exits 0.

Executors. The bridge and the agent, the two ends of the lockstep round trip, spin on rclpy's
``EventsExecutor`` (``rclpy.experimental``, C++): rclpy's ``SingleThreadedExecutor`` rebuilds its
wait set in Python at every ``spin_once``, which was most of the graph's overhead per step
(``bench/graph.py``: the lockstep graph went from ~0.7x to ~1.1-1.3x the in-process loop). In
rclpy 7.1 it does not support subscription callbacks that take the ``MessageInfo`` ("SystemError:
null argument to internal routine") nor a timer destroyed from its own callback, so nodes on it use
one-argument callbacks and cancel timers instead. The recorder, which reads ``MessageInfo`` for the
receive time, stays on ``SingleThreadedExecutor``. ``DER_ROS_EXECUTOR=single|events`` overrides the
choice for every node (debugging).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from der_ros.configuration import ConfigError
from der_ros.nodes.orphans import stop_with_supervisor

__all__ = ["BackgroundNode", "EXECUTORS", "ManagedNode", "install_stop_handlers", "make_executor", "run_node"]

#: executors a node can spin on (see the module docstring)
EXECUTORS = ("single", "events")


class ManagedNode(Protocol):
    """What :func:`run_node` needs from a node besides being an ``rclpy.node.Node``."""

    #: set to True by the node when it has finished its work (e.g. ``max_steps`` reached)
    finished: bool
    # optional ``drain_seconds: float``: keep spinning that long after a signal, to handle
    # messages already queued, before ``on_shutdown``

    def on_shutdown(self, reason: str) -> None: ...


def install_stop_handlers() -> dict[str, str]:
    """SIGINT/SIGTERM handlers that only record the signal's name under ``"reason"`` in the
    returned dict (the spin loop checks it), and the supervisor watch: SIGTERM when ``der graph``
    dies, even by SIGKILL (:mod:`der_ros.nodes.orphans`)."""
    stop: dict[str, str] = {}

    def on_signal(signum: int, _frame: Any) -> None:
        stop["reason"] = signal.Signals(signum).name

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    if not stop_with_supervisor():
        stop["reason"] = "supervisor gone"
    return stop


def make_executor(kind: str) -> Any:
    """A fresh rclpy executor of ``kind`` ('single' or 'events'), or of ``$DER_ROS_EXECUTOR`` when set."""
    kind = os.environ.get("DER_ROS_EXECUTOR") or kind
    if kind not in EXECUTORS:
        raise ConfigError(f"executor = {kind!r} (DER_ROS_EXECUTOR?), expected one of {', '.join(EXECUTORS)}")
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    from rclpy.executors import SingleThreadedExecutor

    return SingleThreadedExecutor()


def run_node(
    factory: Callable[[], Any], argv: Sequence[str] | None = None, poll_s: float = 0.1, executor_kind: str = "single"
) -> int:
    """Create the node with ``factory`` (after ``rclpy.init``) and spin it on an ``executor_kind`` executor.

    Returns the process exit code: 0 after a signal or when the node set ``finished``, 1 if
    the node could not be created (bad parameters: the error is logged, not a traceback), or the
    node's own ``exit_code`` when it sets one (the agent after its learner diverged).
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    args = list(sys.argv if argv is None else argv)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = install_stop_handlers()
    try:
        node = factory()
    except (ConfigError, ValueError, OSError) as exc:  # bad parameters, an unreadable checkpoint_in...
        rclpy.logging.get_logger("der_ros").error(f"could not start: {exc}")
        rclpy.try_shutdown()
        return 1
    executor = make_executor(executor_kind)
    executor.add_node(node)
    reason = "finished"
    try:
        while not node.finished and "reason" not in stop:
            executor.spin_once(timeout_sec=poll_s)
        reason = stop.get("reason", "finished")
        # Nodes that consume a stream (the agent) handle what is already queued before they stop.
        drain_until = time.monotonic() + float(getattr(node, "drain_seconds", 0.0))
        while time.monotonic() < drain_until:
            executor.spin_once(timeout_sec=0.02)
    except (KeyboardInterrupt, ExternalShutdownException):
        reason = "interrupted"
    finally:
        try:
            node.on_shutdown(reason)
        finally:
            executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
            rclpy.try_shutdown()
            # The node is done and its exit code decided. Python's finalisation (seconds with torch
            # loaded) puts SIG_DFL back for handlers it installed, so a Ctrl-C arriving then killed
            # the process by SIGINT (exit -2 instead of the node's code); ignored handlers it keeps.
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.SIG_IGN)
    return int(getattr(node, "exit_code", 0))


class BackgroundNode:
    """An rclpy node in its own ``Context`` and domain, spun by a single-threaded executor in a daemon thread.

    For processes whose main thread is not ROS (the ``der graph`` supervisor, the test process).
    Create subscriptions/publishers on :attr:`node`, then :meth:`start` the spin thread (entities
    may also be added while it runs); :meth:`close` shuts the context down and joins the thread.
    ``handle_signals=False`` keeps rclpy from installing its own SIGINT/SIGTERM handlers.
    """

    def __init__(
        self,
        name: str,
        domain_id: int,
        *,
        namespace: str | None = None,
        spin_timeout: float = 0.1,
        thread_name: str = "rclpy-spin",
        handle_signals: bool = True,
    ) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.context = Context()
        init_kwargs: dict[str, Any] = {}
        if not handle_signals:
            from rclpy.signals import SignalHandlerOptions

            init_kwargs["signal_handler_options"] = SignalHandlerOptions.NO
        rclpy.init(context=self.context, domain_id=domain_id, **init_kwargs)
        self.node = Node(name, namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._spin_timeout = spin_timeout
        self._thread = threading.Thread(target=self._spin, name=thread_name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=self._spin_timeout)
        except Exception:  # context shut down under us while closing
            pass

    def close(self) -> None:
        import rclpy

        try:
            rclpy.shutdown(context=self.context)
        except Exception:  # already shut down
            pass
        self._thread.join(timeout=5)
        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
