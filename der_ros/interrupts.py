"""SIGINT and SIGTERM handlers of the ``der`` processes, installed explicitly.

Why explicitly: a process started in the background by a non-interactive shell (``der graph
... &`` in a script, CI, a test runner that was itself started so) inherits SIGINT *ignored*,
and Python then leaves it ignored -- ``KeyboardInterrupt`` never comes, and ``kill -INT`` does
nothing. Each entry point therefore installs its handlers itself instead of relying on the
inherited disposition; SIGTERM (what ``kill``, systemd and process supervisors send) stops a
``der`` command the same orderly way as Ctrl-C. Node processes install their own (flag-setting)
handlers in :func:`der_ros.nodes.spin.install_stop_handlers`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["raise_interrupt", "interrupts_raise"]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def raise_interrupt(_signum: int, _frame: Any) -> None:
    """A signal handler that turns the signal into ``KeyboardInterrupt`` (the Ctrl-C path)."""
    raise KeyboardInterrupt


@contextmanager
def interrupts_raise() -> Iterator[bool]:
    """Within the block SIGINT and SIGTERM raise ``KeyboardInterrupt``, whatever was inherited;
    the previous handlers come back afterwards. Yields False (and changes nothing) outside the
    main thread, where Python cannot set handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield False
        return
    previous = {sig: signal.getsignal(sig) for sig in _SIGNALS}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, raise_interrupt)
    try:
        yield True
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
