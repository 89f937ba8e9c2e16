"""Offline builds of the SUMO networks shipped with der_ros, cached by a hash of their sources.

Two networks (paper section 5.1):

``ring``
    Two concentric lanes on a closed ring of radius 60 m (~377 m lap), four quarter-arc edges
    driven counter-clockwise so lane 0 is the outer lane and lane 1 the inner one. Sources:
    ``networks/ring/ring.{nod,edg}.xml`` (built with ``netconvert``) and ``ring.rou.xml``
    (vehicle types and looping routes; vehicles are placed by the environment at reset).
``urban``
    A **synthetic stand-in** for the paper's OpenStreetMap extract around Yeongdong Bridge,
    Seoul (no internet on the build machines): the hand-made ``networks/urban/
    yeongdong_synthetic.osm`` describes a straight ~1 km bridge with 3 lanes each way, its
    approach roads and two priority junctions with riverside cross streets. It is imported
    with ``netconvert --osm-files ... --type-files $SUMO_HOME/data/typemap/osmNetconvert.typ.xml``
    and background traffic (``urban.rou.xml``: routes between the fringe edges and random
    ``flow``\\ s) is generated from it by :func:`_write_urban_routes` with a fixed seed.

Builds are cached in ``sumo_bridge/networks/build/<name>/`` (git-ignored) or, when the package
directory is not writable, in ``$XDG_CACHE_HOME/der_ros/networks/<name>/``. A ``stamp.json``
holds the SHA-256 of the sources, of this module (the recipe), the netconvert version and
:data:`BUILD_VERSION`; any change rebuilds. A file lock makes parallel processes (multi-seed runs) build once.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import json
import logging
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "NETWORK_NAMES",
    "BUILD_VERSION",
    "SumoNotFoundError",
    "NetworkBuildError",
    "BuiltNetwork",
    "sumo_home",
    "sumo_binary",
    "netconvert_version",
    "source_dir",
    "cache_root",
    "build_network",
    "build_scenario_network",
]

NETWORK_NAMES: tuple[str, ...] = ("ring", "urban")
#: Bump when the build recipe (options, route generator) changes, to invalidate old caches.
BUILD_VERSION = 1

PACKAGE_DIR = Path(__file__).resolve().parent
SOURCES: dict[str, tuple[str, ...]] = {
    "ring": ("ring.nod.xml", "ring.edg.xml", "ring.rou.xml"),
    "urban": ("yeongdong_synthetic.osm",),
}

#: The urban ego drives north over the bridge (OSM way 100 -> SUMO edge "100").
URBAN_BRIDGE_EDGES: tuple[str, ...] = ("100", "-100")
URBAN_EGO_ROUTE: tuple[str, ...] = ("100", "103", "104")
#: Seed of the urban background-traffic generator (fixed: the route file is part of the build).
URBAN_TRAFFIC_SEED = 20210514


class SumoNotFoundError(RuntimeError):
    """SUMO (the ``eclipse-sumo`` wheel or a SUMO_HOME install) or one of its binaries is missing."""

    user_facing = True  # the `der` CLI prints the message, not a traceback


class NetworkBuildError(RuntimeError):
    """netconvert (or the route generation) failed; the message carries netconvert's stderr."""

    user_facing = True


@dataclass(frozen=True)
class BuiltNetwork:
    """Paths of a built network, ready for ``sumo -n net_file -r route_file``."""

    name: str
    directory: Path
    net_file: Path
    route_file: Path
    stamp: str


def sumo_home() -> Path:
    """SUMO_HOME, set by importing the ``sumo`` wheel package when it is installed."""
    try:
        import sumo  # noqa: F401  (sets SUMO_HOME to the wheel's folder with bin/, data/, tools/)
    except ImportError:
        pass
    home = os.environ.get("SUMO_HOME")
    if not home or not Path(home).is_dir():
        raise SumoNotFoundError(
            "SUMO not found: install the 'eclipse-sumo' wheel (pip install eclipse-sumo libsumo sumolib traci) "
            f"or set SUMO_HOME to a SUMO installation (SUMO_HOME={home!r})"
        )
    os.environ.setdefault("PROJ_LIB", str(Path(home) / "data" / "proj"))
    return Path(home)


def sumo_binary(name: str) -> str:
    """Absolute path of a SUMO binary (``sumo``, ``sumo-gui``, ``netconvert``); clear error if absent."""
    sumo_home()
    import sumolib

    path = sumolib.checkBinary(name)
    if not Path(path).is_file() and shutil.which(path) is None:
        raise SumoNotFoundError(
            f"SUMO binary {name!r} not found (looked for {path!r}); install the 'eclipse-sumo' wheel "
            "or put SUMO's bin/ folder on PATH"
        )
    return path


@functools.lru_cache(maxsize=1)
def netconvert_version() -> str:
    """First line of ``netconvert --version`` (part of the cache stamp)."""
    exe = sumo_binary("netconvert")
    proc = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60)
    lines = (proc.stdout or proc.stderr).strip().splitlines()
    return lines[0] if lines else "unknown"


def source_dir(name: str) -> Path:
    _check_name(name)
    return PACKAGE_DIR / "networks" / name


def _check_name(name: str) -> None:
    if name not in NETWORK_NAMES:
        raise ValueError(f"unknown network {name!r}; expected one of {', '.join(NETWORK_NAMES)}")


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=path, prefix=".probe", delete=True)
        probe.close()
        return True
    except OSError:
        return False


def cache_root() -> Path:
    """Where builds go: the package's ``networks/build`` if writable, else the user cache dir."""
    override = os.environ.get("DER_ROS_NETWORK_CACHE")
    if override:
        return Path(override)
    local = PACKAGE_DIR / "networks" / "build"
    if _writable(local):
        return local
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "der_ros" / "networks"


def _stamp(name: str) -> str:
    digest = hashlib.sha256()
    digest.update(f"build={BUILD_VERSION};netconvert={netconvert_version()};".encode())
    digest.update(Path(__file__).read_bytes())  # the recipe itself (options, route generator)
    for fname in SOURCES[name]:
        digest.update(fname.encode())
        digest.update((source_dir(name) / fname).read_bytes())
    return digest.hexdigest()


def _outputs(name: str, directory: Path) -> tuple[Path, Path]:
    return directory / f"{name}.net.xml", directory / f"{name}.rou.xml"


def build_network(name: str, force: bool = False, cache_dir: Path | None = None) -> BuiltNetwork:
    """Build network ``name`` unless an up-to-date build is cached; returns its paths.

    Raises :class:`SumoNotFoundError` when netconvert is missing and :class:`NetworkBuildError`
    (with netconvert's stderr) when the build fails.
    """
    _check_name(name)
    directory = (cache_dir or cache_root()) / name
    directory.mkdir(parents=True, exist_ok=True)
    stamp = _stamp(name)
    net_file, route_file = _outputs(name, directory)
    stamp_file = directory / "stamp.json"
    with open(directory / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            current = json.loads(stamp_file.read_text()).get("stamp") if stamp_file.is_file() else None
        except (OSError, ValueError):
            current = None
        if force or current != stamp or not net_file.is_file() or not route_file.is_file():
            log.info("building SUMO network %r in %s", name, directory)
            stamp_file.unlink(missing_ok=True)
            if name == "ring":
                _build_ring(directory)
            else:
                _build_urban(directory)
            tmp = stamp_file.with_suffix(".tmp")
            tmp.write_text(json.dumps({"stamp": stamp, "netconvert": netconvert_version(), "build": BUILD_VERSION}))
            tmp.replace(stamp_file)
    return BuiltNetwork(name=name, directory=directory, net_file=net_file, route_file=route_file, stamp=stamp)


def build_scenario_network(name: str, net: Path | None, nodes: Path | None, edges: Path | None,
                           connections: Path | None, demand: tuple[Path, ...]) -> BuiltNetwork:
    """The network of a scenario file (:mod:`sumo_bridge.scenario_file`): a ready ``.net.xml`` is used in
    place; plain sources are built with netconvert into ``<cache>/<name>-<hash of the sources>/`` (built
    once, like the shipped networks). The directory also holds the scenario's warmed traffic states."""
    digest = hashlib.sha256(f"build={BUILD_VERSION};netconvert={netconvert_version()};".encode())
    for path in (net, nodes, edges, connections, *demand):
        if path is not None:
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    stamp = digest.hexdigest()
    directory = cache_root() / f"{name}-{stamp[:12]}"
    directory.mkdir(parents=True, exist_ok=True)
    route_file = demand[0] if demand else directory / "empty.rou.xml"
    if net is not None:
        return BuiltNetwork(name=name, directory=directory, net_file=net, route_file=route_file, stamp=stamp)
    assert nodes is not None and edges is not None
    net_file = directory / f"{name}.net.xml"
    with open(directory / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not net_file.is_file():
            log.info("building SUMO network of scenario %r in %s", name, directory)
            args = ["--node-files", str(nodes), "--edge-files", str(edges)]
            if connections is not None:
                args += ["--connection-files", str(connections)]
            _run_netconvert(args, net_file)
    return BuiltNetwork(name=name, directory=directory, net_file=net_file, route_file=route_file, stamp=stamp)


def _run_netconvert(args: list[str], output: Path) -> None:
    exe = sumo_binary("netconvert")
    tmp = output.with_name(output.name + ".tmp")
    cmd = [exe, *args, "--no-turnarounds", "true", "--no-warnings", "false", "-o", str(tmp)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetworkBuildError(f"netconvert could not run ({' '.join(cmd)}): {exc}") from exc
    if proc.returncode != 0 or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        raise NetworkBuildError(
            f"netconvert failed with exit code {proc.returncode}: {' '.join(cmd)}\n--- stderr ---\n{proc.stderr.strip()}"
        )
    tmp.replace(output)


def _build_ring(directory: Path) -> None:
    src = source_dir("ring")
    net_file, route_file = _outputs("ring", directory)
    _run_netconvert(
        ["--node-files", str(src / "ring.nod.xml"), "--edge-files", str(src / "ring.edg.xml")],
        net_file,
    )
    shutil.copyfile(src / "ring.rou.xml", route_file)


def _build_urban(directory: Path) -> None:
    home = sumo_home()
    src = source_dir("urban")
    net_file, route_file = _outputs("urban", directory)
    typemap = home / "data" / "typemap" / "osmNetconvert.typ.xml"
    if not typemap.is_file():
        raise SumoNotFoundError(f"SUMO type map {typemap} not found; is SUMO_HOME ({home}) a full SUMO install?")
    _run_netconvert(
        [
            "--osm-files",
            str(src / "yeongdong_synthetic.osm"),
            "--type-files",
            str(typemap),
            "--output.street-names",
            "true",
            "--geometry.remove",
            "true",
            "--junctions.join",
            "false",
            "--tls.guess",
            "false",
        ],
        net_file,
    )
    try:
        _write_urban_routes(net_file, route_file, seed=URBAN_TRAFFIC_SEED)
    except NetworkBuildError:
        raise
    except Exception as exc:  # sumolib parse errors and the like
        raise NetworkBuildError(f"generating urban background traffic from {net_file} failed: {exc}") from exc


#: Vehicle types of the urban network (same ego/car/slow mix as the ring's ring.rou.xml).
_URBAN_VTYPES = """\
    <vType id="ego" vClass="passenger" color="1,0,0" length="5" minGap="2.5" accel="2.6" decel="4.5" emergencyDecel="9" sigma="0.5" speedFactor="1.0" speedDev="0"/>
    <vType id="car" vClass="passenger" color="1,1,0" length="5" minGap="2.5" accel="2.6" decel="4.5" emergencyDecel="9" sigma="0.5" speedFactor="1.0" speedDev="0.1"/>
    <vType id="slow" vClass="passenger" color="0,0.6,1" length="7" minGap="2.5" accel="1.8" decel="4.0" emergencyDecel="9" sigma="0.5" speedFactor="0.7" speedDev="0.1"/>
"""


def _unopposed(path: list) -> bool:
    """True if the route turns only right or goes straight along the main axis.

    Left turns and minor-road crossings at the priority junctions have to wait for gaps in
    three lanes of main-road traffic; with teleporting off they queue without end.
    """
    for a, b in zip(path[:-1], path[1:]):
        conns = a.getConnections(b)
        if not conns:
            return False
        direction = conns[0].getDirection().lower()
        if direction not in ("s", "r"):
            return False
        if direction == "s" and a.getType() != b.getType():
            return False
        if direction == "s" and "secondary" in (a.getType() or ""):
            return False  # crossing the main road from a minor road
    return True


def _write_urban_routes(net_file: Path, route_file: Path, seed: int) -> None:
    """Background traffic for the urban network: one random ``flow`` per origin/destination pair.

    Our own small generator (instead of randomTrips.py) so the demand is shaped for the task:
    most traffic drives the main axis over the bridge (northbound is what the ego sees), a
    little turns right at the junctions (see :func:`_unopposed`). Flows use ``probability`` (a Bernoulli insertion per second), so each SUMO
    ``--seed`` gives different traffic while the file itself is fixed by ``seed``.
    """
    import sumolib

    net = sumolib.net.readNet(str(net_file))
    rng = np.random.default_rng(seed)
    # Entries and exits at the fringe of the network (edges starting/ending at a dead-end node).
    edges = [e for e in net.getEdges() if not e.getID().startswith(":")]
    sources = sorted((e for e in edges if not e.getIncoming()), key=lambda e: e.getID())
    sinks = sorted((e for e in edges if not e.getOutgoing()), key=lambda e: e.getID())
    if not sources or not sinks:
        raise NetworkBuildError(f"{net_file}: no fringe edges found for background traffic")
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<!-- generated by sumo_bridge.network_build; do not edit -->", "<routes>"]
    lines.append(_URBAN_VTYPES.rstrip("\n"))
    lines.append(f'    <route id="ego_route" edges="{" ".join(URBAN_EGO_ROUTE)}"/>')
    n_routes = 0
    for src in sources:
        for dst in sinks:
            path, _cost = net.getShortestPath(src, dst)
            if not path or dst.getID() == "-" + src.getID() or src.getID() == "-" + dst.getID():
                continue
            if not _unopposed(path):
                continue
            ids = [e.getID() for e in path]
            main_through = ids[0] in ("101", "-104") and ids[-1] in ("104", "-101")
            # veh/s inserted by this flow: the main axis carries the bridge traffic, turns are light
            if main_through and ids[0] == "101":  # northbound: the ego's traffic
                rate = rng.uniform(0.95, 1.1)
            elif main_through:  # southbound: scenery for the ego, kept light for speed
                rate = rng.uniform(0.35, 0.45)
            elif ids[0] in ("101", "-104"):
                rate = rng.uniform(0.03, 0.08)
            else:  # entering from a minor road: must find gaps in the main traffic
                rate = rng.uniform(0.005, 0.015)
            rid = f"r{n_routes}_{ids[0]}_{ids[-1]}"
            lines.append(f'    <route id="{rid}" edges="{" ".join(ids)}"/>')
            for vtype, share in (("car", 0.8), ("slow", 0.2)):
                prob = min(0.95, rate * share)
                lines.append(
                    f'    <flow id="f_{rid}_{vtype}" route="{rid}" type="{vtype}" begin="0" end="1000000" '
                    f'probability="{prob:.4f}" departLane="free" departSpeed="max" departPos="base"/>'
                )
            n_routes += 1
    lines.append("</routes>")
    if n_routes == 0:
        raise NetworkBuildError(f"{net_file}: no route between the fringe edges")
    tmp = route_file.with_name(route_file.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(route_file)
