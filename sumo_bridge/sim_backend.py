"""One SUMO simulation behind one interface: libsumo in process, or traci over a socket.

Both backends expose the same TraCI domain API (``sim.api.vehicle``, ``sim.api.simulation``,
...), so the environment runs the very same code on either (``backend="traci"`` is for
``sumo-gui`` and for cross-checking; ``libsumo`` is ~10-20x faster).

libsumo keeps its simulation in process-global C++ state: a second ``libsumo.start()`` silently
replaces the first one (checked on SUMO 1.28). :class:`SumoSimulation` therefore holds a
process-wide slot: while one libsumo simulation is open, opening another raises
:class:`SimulationInUseError`; closing the first frees the slot. For parallel environments use
one process per environment (subprocesses, e.g. gymnasium's ``AsyncVectorEnv``). traci
simulations each get their own ``sumo`` subprocess and connection label, so several can coexist.
"""

from __future__ import annotations

import itertools
import logging
import os
import sys
import threading
from types import ModuleType
from typing import Any

from sumo_bridge.network_build import SumoNotFoundError, sumo_binary, sumo_home

log = logging.getLogger(__name__)

__all__ = ["NoDisplayError", "SimulationInUseError", "SumoSimulation", "libsumo_in_use"]

_LOCK = threading.Lock()
_LIBSUMO_OWNER: str | None = None
_LABELS = itertools.count()


class SimulationInUseError(RuntimeError):
    """A second libsumo simulation was requested while one is still open in this process."""


class NoDisplayError(RuntimeError):
    """``gui=True`` on a machine without a display (sumo-gui would exit and traci retry for a minute)."""

    user_facing = True  # the `der` CLI prints the message, not a traceback


def _check_display() -> None:
    """Fail fast and clearly where sumo-gui cannot open a window (Linux/X11/Wayland only)."""
    if not sys.platform.startswith("linux"):
        return
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise NoDisplayError(
            "gui = True needs a display, but neither DISPLAY nor WAYLAND_DISPLAY is set: run on a desktop, "
            "over ssh -X, or under xvfb-run; or set gui = False (record a bag and replay it in Foxglove instead)"
        )


def libsumo_in_use() -> str | None:
    """Description of the open libsumo simulation's owner, or None."""
    return _LIBSUMO_OWNER


class SumoSimulation:
    """A started SUMO simulation; ``api`` is the libsumo module or a traci ``Connection``."""

    def __init__(self, args: list[str], backend: str = "libsumo", gui: bool = False, owner: str = "") -> None:
        """Start SUMO with ``args`` (without the binary name).

        ``gui=True`` runs ``sumo-gui`` and requires (implies) the traci backend.
        """
        global _LIBSUMO_OWNER
        if gui:
            backend = "traci"
        if backend not in ("libsumo", "traci"):
            raise ValueError(f"backend = {backend!r}, expected 'libsumo' or 'traci'")
        self.backend = backend
        self.gui = gui
        self.owner = owner or f"pid {os.getpid()}"
        self._closed = True
        self._label: str | None = None
        sumo_home()
        if backend == "libsumo":
            with _LOCK:
                if _LIBSUMO_OWNER is not None:
                    raise SimulationInUseError(
                        f"a libsumo simulation is already open in this process (owner: {_LIBSUMO_OWNER}); libsumo "
                        "supports one simulation per process. Close the first environment, use backend='traci', "
                        "or run parallel environments in subprocesses."
                    )
                _LIBSUMO_OWNER = self.owner
            try:
                import libsumo
            except ImportError as exc:
                with _LOCK:
                    _LIBSUMO_OWNER = None
                raise SumoNotFoundError(f"libsumo is not importable ({exc}); pip install libsumo") from exc
            try:
                libsumo.start(["sumo", *args])
            except Exception:
                with _LOCK:
                    _LIBSUMO_OWNER = None
                raise
            self.api: Any = libsumo
        else:
            import traci

            if gui:
                _check_display()
            binary = sumo_binary("sumo-gui" if gui else "sumo")
            self._label = f"der_ros_{os.getpid()}_{next(_LABELS)}"
            try:
                traci.start([binary, *args], label=self._label)
            except traci.exceptions.FatalTraCIError as exc:
                if not gui:
                    raise
                raise NoDisplayError(
                    f"sumo-gui did not start ({exc}); is the display DISPLAY={os.environ.get('DISPLAY', '')!r} "
                    "reachable? Set gui = False to run without a window"
                ) from exc
            self.api = traci.getConnection(self._label)
        self._closed = False
        log.debug("started SUMO (%s) for %s", backend, self.owner)

    @property
    def closed(self) -> bool:
        return self._closed

    def load(self, args: list[str]) -> None:
        """Restart the simulation in place with new ``args`` (no new process; libsumo ~ms)."""
        self._check_open()
        self.api.load(list(args))

    def close(self) -> None:
        """Stop SUMO and free the libsumo slot (idempotent)."""
        global _LIBSUMO_OWNER
        if self._closed:
            return
        self._closed = True
        try:
            self.api.close()
        except Exception as exc:  # a dead traci subprocess; nothing left to free but the slot
            log.debug("closing SUMO (%s): %s", self.backend, exc)
        finally:
            if self.backend == "libsumo":
                with _LOCK:
                    _LIBSUMO_OWNER = None

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("the SUMO simulation is closed")

    def __del__(self) -> None:  # free the slot if an env is dropped without close()
        try:
            self.close()
        except Exception:
            pass


def constants() -> ModuleType:
    """TraCI constants (identical values for libsumo and traci)."""
    import traci.constants as tc

    return tc
