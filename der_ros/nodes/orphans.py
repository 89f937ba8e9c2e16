"""Node processes stop when their ``der graph`` supervisor dies, even if it is SIGKILLed.

The supervisor starts every child in a session of its own (so a terminal Ctrl-C reaches only
the supervisor, which then stops the children in order). The price is that a supervisor killed
with SIGKILL (OOM killer, ``kill -9``, a CI timeout) cannot stop anybody: its nodes would keep
running, publishing and holding the SUMO simulation and the bag.

So the supervisor puts its pid in each child's environment (:data:`SUPERVISOR_PID_ENV`), and
the node executables call :func:`stop_with_supervisor` at start-up. On Linux that asks the
kernel (``prctl(PR_SET_PDEATHSIG)``) to send the node SIGTERM when the supervisor goes away;
the node then shuts down as on any SIGTERM (agent checkpoint, recorder bag finalised). The
setting is made in the child after ``exec``, not in a ``preexec_fn``, because the supervisor
has threads (DDS, the graph monitor) and forking with a Python callback is unsafe then.

Without the variable (a node started by hand or by ``ros2 launch``) nothing changes. On other
systems the call is a no-op that returns True.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys

__all__ = ["SUPERVISOR_PID_ENV", "stop_with_supervisor"]

log = logging.getLogger(__name__)

#: Environment variable holding the pid of the ``der graph`` supervisor that started the node.
SUPERVISOR_PID_ENV = "DER_ROS_SUPERVISOR_PID"
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def stop_with_supervisor(signum: int = signal.SIGTERM) -> bool:
    """Have ``signum`` delivered to this process when its supervisor exits (Linux).

    Returns False if this process was started by a supervisor that is already gone (its parent
    is no longer the pid in :data:`SUPERVISOR_PID_ENV`): the caller should stop at once. True
    otherwise, including when there is no supervisor or the platform has no ``prctl``.
    """
    raw = os.environ.get(SUPERVISOR_PID_ENV)
    if not raw:
        return True
    try:
        supervisor = int(raw)
    except ValueError:
        log.warning("%s = %r is not a pid; not watching the supervisor", SUPERVISOR_PID_ENV, raw)
        return True
    if not sys.platform.startswith("linux"):
        return True
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0) != 0:
            err = ctypes.get_errno()
            log.warning("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(err))
            return True
    except (OSError, AttributeError) as exc:
        log.warning("prctl is not available (%s); not watching the supervisor", exc)
        return True
    # the supervisor may have died between our fork and the prctl call: then no signal will come
    return os.getppid() == supervisor
