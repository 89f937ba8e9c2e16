"""Scenarios as data: read a scenario file (YAML beside SUMO sources) into a checked :class:`ScenarioSpec`.

A scenario file names the road, the traffic, the ego and its goal; :func:`load_scenario` checks
all of it *before* SUMO starts (files exist, the ego's lane exists on its first edge, the goal
edge is on the ego's route and reachable, the YAML parses) and raises one
:class:`ScenarioFileError` naming the file, the field and, where it can, the line. The format
reference is ``docs/scenarios.md``; the shipped scenarios are ``sumo_bridge/scenarios/*.yaml``.

Layout (paths relative to the scenario file)::

    name: exit                          # the scenario's name (tables, run folders)
    network:                            # one of:
      builtin: ring                     #   a built-in network (ring, urban: their code-built set-up)
      net: road.net.xml                 #   a ready SUMO network
      nodes: r.nod.xml                  #   plain sources built with netconvert (cached by content)
      edges: r.edg.xml
      connections: r.con.xml            #   (optional)
    demand: [road.rou.xml]              # vehicle types, routes, flows of the background traffic
    ego:
      route: [approach, ramp]           # edges; the ego is a vehicle on route[0] taken over at reset
      lane: leftmost                    # lane index on route[0], or 'leftmost' / 'rightmost'
      type: ego                         # vType of the ego (defined in the demand)
      depart_pos: [100, 200]            # window (m along route[0]) the ego is chosen in
    goal:                               # one of:
      lane: 1                           #   reach this lane index (ring, urban)
      edge: ramp                        #   reach this edge of the route (an exit)
    horizon: 60                         # decisions per episode (max_episode_steps)
    reward: {success: 100, collision: -100, missed: 0, min_speed: 0.1}
    actions: [keep, left, right]        # or [keep, left, right, faster, slower]
    traffic: {warmup_seconds: 120, ego_gap_seconds: 1, miss_zone: 100, halt_speed: 0.5, halt_seconds: 2,
              teleport_seconds: 20}
    settings: {...}                     # any other sumo_bridge.scenario.ScenarioConfig field
    safety: {unobserved_speed: 25, lane_end: true}  # the fleet's worst case for the RSS shield (optional;
                                        # der_ros.safety.config.fleet_cautious: the more cautious value wins)

YAML is read by :func:`read_yaml_text` (the project-wide strict loader, :mod:`der_ros.yaml_loader`).
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from der_ros.configuration import ConfigError, from_dict, to_dict, validate
from der_ros.yaml_loader import YamlError, load_yaml_text
from sumo_bridge.network_build import NETWORK_NAMES
from sumo_bridge.scenario import ACTION_SETS, ScenarioConfig
from sumo_bridge.scenario import scenario_from_kwargs as _config_from_kwargs

__all__ = [
    "ScenarioFileError",
    "ScenarioSpec",
    "EgoSpec",
    "GoalSpec",
    "TrafficSpec",
    "NetworkSource",
    "read_yaml_text",
    "load_scenario",
    "load_scenario_config",
    "shipped_scenario",
    "scenario_from_kwargs",
    "SHIPPED_DIR",
]

#: Scenario files shipped with the package (``ring``, ``urban``, ``exit``).
SHIPPED_DIR = Path(__file__).resolve().parent / "scenarios"
_TOP_KEYS = ("name", "network", "demand", "ego", "goal", "horizon", "reward", "actions", "traffic", "settings", "safety")
#: ``safety:`` keys (the RSS parameters that describe a fleet; der_ros.safety.config.FLEET_FIELDS) and their
#: lowest allowed values (a braking must be > 0: ``low`` is exclusive for those)
SAFETY_KEYS: dict[str, tuple[float, bool]] = {"response_time": (0.0, True), "accel_max": (0.0, True),
                                              "brake_min": (0.0, False), "brake_max": (0.0, False),
                                              "unobserved_speed": (0.0, True), "unobserved_brake": (0.0, False),
                                              "lane_end": (0.0, True), "beyond_lane": (0.0, True),
                                              "ego_brake": (0.0, False)}  # fmt: skip  (lane_end, beyond_lane: true / false)
_REWARD_FIELDS = {"success": "reward_success", "collision": "reward_collision", "missed": "reward_missed",
                  "min_speed": "min_speed"}  # fmt: skip


class ScenarioFileError(ConfigError):
    """A scenario file is unreadable or inconsistent; the message is one line: file[:line]: field: problem."""

    user_facing = True


@dataclass(frozen=True)
class NetworkSource:
    """Where the road comes from: exactly one of ``builtin``, ``net``, or ``nodes`` + ``edges``."""

    builtin: str = ""
    net: Path | None = None
    nodes: Path | None = None
    edges: Path | None = None
    connections: Path | None = None


@dataclass(frozen=True)
class EgoSpec:
    """The ego: its route (edge ids), start lane, vType and the window it is chosen in on ``route[0]``."""

    route: tuple[str, ...] = ()
    lane: int = 0
    type: str = "ego"
    depart_pos: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class GoalSpec:
    """The goal: a lane index (``lane``) or an edge of the ego's route (``edge``; ``lanes``: the lanes of
    the edge before it that lead onto it, the ones the ego must be on at the diverge)."""

    lane: int | None = None
    edge: str | None = None
    lanes: tuple[int, ...] = ()


@dataclass(frozen=True)
class TrafficSpec:
    """Background traffic timing and the 'missed' rule of an edge goal."""

    warmup_seconds: float = 120.0
    """simulated seconds of traffic after a load before the warmed state is saved (one per traffic seed)"""
    ego_gap_seconds: float = 1.0
    """seconds of traffic between one episode's ego leaving and the next one taken over (unseeded resets)"""
    miss_zone: float = 100.0
    """metres before the diverge where halting on a lane that does not lead to the goal is a miss"""
    halt_speed: float = 0.5
    """m/s below which the ego counts as halted"""
    halt_seconds: float = 2.0
    """seconds halted (in the miss zone, on a wrong lane) that make a miss"""
    teleport_seconds: float = -1.0
    """SUMO's --time-to-teleport: a vehicle blocked this long is moved on (-1 = never; the ego's episode
    ends as missed long before)"""


@dataclass(frozen=True)
class ScenarioSpec:
    """A checked scenario file: its parts and the :class:`ScenarioConfig` the env runs."""

    path: Path
    name: str
    network: NetworkSource
    demand: tuple[Path, ...]
    ego: EgoSpec
    goal: GoalSpec
    traffic: TrafficSpec
    config: ScenarioConfig
    lane_counts: dict[str, int] = field(default_factory=dict)
    safety: dict[str, Any] = field(default_factory=dict)
    """the ``safety:`` section: the fleet's worst case for the RSS shield (only the keys the file gives)"""


def read_yaml_text(path: Path) -> Any:
    """The scenario file read by the project's one YAML loader (:mod:`der_ros.yaml_loader`: duplicate
    keys, depth and size limits, YAML 1.2 numbers); any refusal becomes one line naming the file and line."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioFileError(f"{path}: cannot read the scenario file ({exc.strerror or exc})") from None
    try:
        return load_yaml_text(text, str(path))
    except YamlError as exc:
        raise ScenarioFileError(str(exc)) from None


def _line_of(path: Path, dotted: str) -> int | None:
    """1-based line of key ``a.b.c`` in the YAML file (None if not found)."""
    try:
        node = yaml.compose(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    line = None
    for part in dotted.split("."):
        if not isinstance(node, yaml.MappingNode):
            break
        for key, value in node.value:
            if key.value == part:
                line, node = key.start_mark.line + 1, value
                break
        else:
            break
    return line


def _fail(path: Path, key: str, message: str) -> ScenarioFileError:
    line = _line_of(path, key)
    where = f"{path}:{line}" if line else str(path)
    return ScenarioFileError(f"{where}: {key}: {message}", key=key, reason=message)


def _mapping(path: Path, data: Any, key: str, allowed: tuple[str, ...]) -> dict[str, Any]:
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise _fail(path, key, f"{data!r}, expected a mapping")
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise _fail(path, f"{key}.{unknown[0]}", f"unknown key, expected one of {', '.join(allowed)}")
    return data


def _file(path: Path, key: str, value: Any) -> Path:
    if not isinstance(value, str) or not value:
        raise _fail(path, key, f"{value!r}, expected a file name")
    out = (path.parent / value).resolve()
    if not out.is_file():
        raise _fail(path, key, f"file {value!r} not found (looked for {out})")
    return out


def _read_network(path: Path, src: NetworkSource) -> tuple[dict[str, int], dict[str, set[tuple[int, str]]] | None]:
    """Lane count of every normal edge, and the lane connections ``(edge) -> {(from lane, to edge)}``
    (None when the sources do not say: netconvert guesses them)."""
    lanes: dict[str, int] = {}
    links: dict[str, set[tuple[int, str]]] = {}
    try:
        if src.net is not None:
            root = ET.parse(src.net).getroot()
            for edge in root.iter("edge"):
                if edge.get("function") == "internal":
                    continue
                lanes[str(edge.get("id"))] = len(edge.findall("lane"))
            for con in root.iter("connection"):
                frm = str(con.get("from"))
                if frm.startswith(":"):
                    continue
                links.setdefault(frm, set()).add((int(con.get("fromLane", 0)), str(con.get("to"))))
            return lanes, links
        assert src.edges is not None
        for edge in ET.parse(src.edges).getroot().iter("edge"):
            lanes[str(edge.get("id"))] = int(edge.get("numLanes", 1))
        if src.connections is None:
            return lanes, None
        for con in ET.parse(src.connections).getroot().iter("connection"):
            frm = str(con.get("from"))
            from_lanes = [int(con.get("fromLane"))] if con.get("fromLane") is not None else range(lanes.get(frm, 1))
            for k in from_lanes:
                links.setdefault(frm, set()).add((k, str(con.get("to"))))
        return lanes, links
    except (ET.ParseError, ValueError) as exc:
        raise _fail(path, "network", f"cannot read the network sources ({exc})") from None


def _network(path: Path, data: Any) -> NetworkSource:
    if isinstance(data, str):
        data = {"builtin": data} if data in NETWORK_NAMES else {"net": data}
    net = _mapping(path, data, "network", ("builtin", "net", "nodes", "edges", "connections"))
    if "builtin" in net:
        if set(net) != {"builtin"} or net["builtin"] not in NETWORK_NAMES:
            raise _fail(path, "network.builtin", f"{net.get('builtin')!r}, expected one of {', '.join(NETWORK_NAMES)} "
                        "and no other network key")  # fmt: skip
        return NetworkSource(builtin=str(net["builtin"]))
    if "net" in net:
        if set(net) != {"net"}:
            raise _fail(path, "network", "give either net or nodes + edges, not both")
        return NetworkSource(net=_file(path, "network.net", net["net"]))
    if "nodes" not in net or "edges" not in net:
        raise _fail(path, "network", "missing: expected builtin, net (a .net.xml) or nodes + edges (plain sources)")
    con = _file(path, "network.connections", net["connections"]) if "connections" in net else None
    return NetworkSource(nodes=_file(path, "network.nodes", net["nodes"]), edges=_file(path, "network.edges", net["edges"]),
                         connections=con)  # fmt: skip


def _number(path: Path, key: str, value: Any, low: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(path, key, f"{value!r}, expected a number")
    if low is not None and value < low:
        raise _fail(path, key, f"{value!r}, expected >= {low}")
    return float(value)


def load_scenario(path: str | Path) -> ScenarioSpec:
    """Read and check a scenario file (see the module docstring); nothing of SUMO is started."""
    path = Path(path).resolve()
    if not path.is_file():
        raise ScenarioFileError(f"{path}: scenario file not found")
    data = read_yaml_text(path)
    top = _mapping(path, data, "scenario", _TOP_KEYS)
    if not top:
        raise ScenarioFileError(f"{path}: empty scenario file, expected the keys {', '.join(_TOP_KEYS)}")
    name = top.get("name")
    if not isinstance(name, str) or not name.replace("_", "").replace("-", "").isalnum():
        raise _fail(path, "name", f"{name!r}, expected a name of letters, digits, '-' and '_'")
    if "network" not in top:
        raise _fail(path, "network", "missing, expected builtin, net or nodes + edges")
    src = _network(path, top["network"])
    builtin = bool(src.builtin)
    if builtin and name != src.builtin:
        raise _fail(path, "name", f"{name!r}, expected {src.builtin!r} for the built-in network (its set-up is named by it)")
    demand_raw = top.get("demand", [])
    demand_raw = [demand_raw] if isinstance(demand_raw, str) else demand_raw
    if not isinstance(demand_raw, list):
        raise _fail(path, "demand", f"{demand_raw!r}, expected a route file or a list of them")
    demand = tuple(_file(path, "demand", d) for d in demand_raw)
    if not builtin and not demand:
        raise _fail(path, "demand", "missing, expected the route file(s) with the ego's vType and the background traffic")
    ego_raw = _mapping(path, top.get("ego"), "ego", ("route", "lane", "type", "depart_pos"))
    goal_raw = _mapping(path, top.get("goal"), "goal", ("lane", "edge"))
    if len(goal_raw) != 1:
        raise _fail(path, "goal", f"{top.get('goal')!r}, expected exactly one of lane or edge")
    lane_counts: dict[str, int] = {}
    links: dict[str, set[tuple[int, str]]] | None = None
    if not builtin:
        lane_counts, links = _read_network(path, src)
    route = ego_raw.get("route", [])
    if not builtin:
        if not isinstance(route, list) or not route or not all(isinstance(e, str) for e in route):
            raise _fail(path, "ego.route", f"{route!r}, expected a list of edge ids")
        for e in route:
            if e not in lane_counts:
                raise _fail(path, "ego.route", f"edge {e!r} is not in the network")
    first_lanes = lane_counts.get(route[0], 0) if route else 0
    lane = ego_raw.get("lane", 0)
    if lane == "leftmost":
        lane = first_lanes - 1 if not builtin else lane
    elif lane == "rightmost":
        lane = 0
    if isinstance(lane, bool) or not isinstance(lane, int) or lane < 0:
        raise _fail(path, "ego.lane", f"{lane!r}, expected a lane index >= 0, 'leftmost' or 'rightmost'")
    if not builtin and lane >= first_lanes:
        raise _fail(path, "ego.lane", f"{lane}: unknown lane, edge {route[0]!r} has lanes 0-{first_lanes - 1}")
    pos = ego_raw.get("depart_pos", [0.0, 0.0])
    if not isinstance(pos, list) or len(pos) != 2:
        raise _fail(path, "ego.depart_pos", f"{pos!r}, expected [min, max] in metres")
    depart_pos = (_number(path, "ego.depart_pos", pos[0], 0.0), _number(path, "ego.depart_pos", pos[1], 0.0))
    if depart_pos[0] > depart_pos[1]:
        raise _fail(path, "ego.depart_pos", f"{pos!r}, expected min <= max")
    goal_lanes: tuple[int, ...] = ()
    if "lane" in goal_raw:
        target = goal_raw["lane"]
        if isinstance(target, bool) or not isinstance(target, int) or target < 0:
            raise _fail(path, "goal.lane", f"{target!r}, expected a lane index >= 0")
        if not builtin and target >= first_lanes:
            raise _fail(path, "goal.lane", f"{target}: unknown lane, edge {route[0]!r} has lanes 0-{first_lanes - 1}")
        goal = GoalSpec(lane=target)
    else:
        edge = goal_raw["edge"]
        if builtin:
            raise _fail(path, "goal.edge", "a built-in network takes a goal lane")
        if edge not in route:
            raise _fail(path, "goal.edge", f"{edge!r} is not on the ego's route {route}")
        k = route.index(edge)
        if k == 0:
            raise _fail(path, "goal.edge", f"{edge!r} is the ego's first edge, expected an edge further along its route")
        before = route[k - 1]
        if links is None:
            goal_lanes = tuple(range(lane_counts[before]))
        else:
            goal_lanes = tuple(sorted(i for i, to in links.get(before, set()) if to == edge))
        if not goal_lanes:
            raise _fail(path, "goal.edge", f"{edge!r} cannot be reached from edge {before!r} (no lane connects them)")
        if lane in goal_lanes:
            raise _fail(path, "ego.lane", f"{lane}: the ego would start on a lane that leads to the goal already")
        goal = GoalSpec(edge=str(edge), lanes=goal_lanes)
    traffic_raw = _mapping(path, top.get("traffic"), "traffic", tuple(f.name for f in dataclasses.fields(TrafficSpec)))
    traffic = TrafficSpec(**{k: _number(path, f"traffic.{k}", v, -1.0 if k == "teleport_seconds" else 0.0)
                             for k, v in traffic_raw.items()})  # fmt: skip
    config = _config(path, top, name, builtin, lane, goal, goal_lanes)
    most = max((lane_counts[e] for e in route), default=0)
    if not builtin and config.observation.max_lanes < most:
        raise _fail(path, "settings.observation.max_lanes", f"{config.observation.max_lanes}, expected >= {most} (the "
                    "most lanes on the ego's route)")  # fmt: skip
    safety = _safety(path, top.get("safety"))
    return ScenarioSpec(path=path, name=name, network=src, demand=demand, ego=EgoSpec(tuple(route), lane, str(ego_raw.get("type", "ego")), depart_pos),
                        goal=goal, traffic=traffic, config=config, lane_counts=lane_counts, safety=safety)  # fmt: skip


def _safety(path: Path, data: Any) -> dict[str, Any]:
    """The ``safety:`` section: numbers within the RSS parameters' ranges, keyed by :data:`SAFETY_KEYS`."""
    out: dict[str, Any] = {}
    for k, v in _mapping(path, data, "safety", tuple(SAFETY_KEYS)).items():
        if k in ("lane_end", "beyond_lane"):
            if not isinstance(v, bool):
                raise _fail(path, f"safety.{k}", f"{v!r}, expected true or false")
            out[k] = v
            continue
        low, inclusive = SAFETY_KEYS[k]
        value = _number(path, f"safety.{k}", v, low)
        if not inclusive and value <= low:
            raise _fail(path, f"safety.{k}", f"{v!r}, expected > {low:g}")
        if value != value or value in (float("inf"), float("-inf")):
            raise _fail(path, f"safety.{k}", f"{v!r}, expected a finite number")
        out[k] = value
    return out


def _config(path: Path, top: dict[str, Any], name: str, builtin: bool, lane: int, goal: GoalSpec,
            goal_lanes: tuple[int, ...]) -> ScenarioConfig:  # fmt: skip
    settings = _mapping(path, top.get("settings"), "settings", tuple(f.name for f in dataclasses.fields(ScenarioConfig)))
    for k in ("network", "file", "ego_lane", "target_lane", "max_episode_steps", "actions") + tuple(_REWARD_FIELDS.values()):
        if k in settings:
            raise _fail(path, f"settings.{k}", "set by the scenario file's own keys (name, ego, goal, horizon, reward, actions)")
    data: dict[str, Any] = dict(settings)
    data["network"] = name
    if not builtin:
        data["file"] = str(path)
    data["ego_lane"] = lane
    data["target_lane"] = goal.lane if goal.lane is not None else goal_lanes[0]
    if builtin and data["target_lane"] == {"ring": 1, "urban": 2}[name]:
        data["target_lane"] = -1  # the built-in's own default: the same config as ScenarioConfig.ring()/.urban()
    if "horizon" in top:
        data["max_episode_steps"] = top["horizon"]
    for k, v in _mapping(path, top.get("reward"), "reward", tuple(_REWARD_FIELDS)).items():
        data[_REWARD_FIELDS[k]] = v
    if "actions" in top:
        acts = top["actions"]
        if not isinstance(acts, list) or tuple(acts) not in ACTION_SETS:
            raise _fail(path, "actions", f"{acts!r}, expected one of {[list(a) for a in ACTION_SETS]}")
        data["actions"] = acts
    try:
        cfg = from_dict(ScenarioConfig, data, source=str(path))
        return validate(cfg, source=str(path))
    except ScenarioFileError:
        raise
    except ConfigError as exc:
        key = exc.key or ""
        inverse = {v: f"reward.{k}" for k, v in _REWARD_FIELDS.items()}
        key = {"max_episode_steps": "horizon", "actions": "actions"}.get(key, inverse.get(key, f"settings.{key}" if key else "settings"))
        raise _fail(path, key, exc.reason or str(exc)) from None


def shipped_scenario(name: str) -> Path:
    """Path of a scenario file shipped with the package (``ring``, ``urban``, ``exit``)."""
    return SHIPPED_DIR / f"{name}.yaml"


def load_scenario_config(path_or_name: str | Path, **overrides: Any) -> ScenarioConfig:
    """The :class:`ScenarioConfig` of a scenario file (or a shipped scenario's name), with field overrides."""
    p = Path(path_or_name)
    if not p.suffix and not p.exists() and shipped_scenario(str(path_or_name)).is_file():
        p = shipped_scenario(str(path_or_name))
    cfg = load_scenario(p).config
    if not overrides:
        return cfg
    data = to_dict(cfg)
    obs = overrides.pop("observation", None)
    data.update(overrides)
    if obs is not None:
        data["observation"] = {**data["observation"], **(to_dict(obs) if not isinstance(obs, dict) else obs)}
    return validate(from_dict(ScenarioConfig, data, source=str(p)), source=str(p))


def scenario_from_kwargs(network: str, config: ScenarioConfig | dict[str, Any] | str | None = None,
                         **overrides: Any) -> ScenarioConfig:  # fmt: skip
    """:func:`sumo_bridge.scenario.scenario_from_kwargs` for every env id: ``network`` 'scenario'
    (``der_ros/LaneChangeScenario-v0``) takes its defaults from the scenario file named by ``file`` in
    ``config`` (or ``config`` itself as a path; a shipped scenario's name works too)."""
    if isinstance(config, str):
        config = {"file": config}
    if network != "scenario":
        return _config_from_kwargs(network, config, **overrides)
    given = to_dict(config) if isinstance(config, ScenarioConfig) else dict(config or {})
    file = given.get("file") or overrides.get("file")
    if not file:
        raise ConfigError("scenario: file missing, expected the path of a scenario file (or a shipped name: exit)")
    base = load_scenario_config(file)

    def preset(**kw: Any) -> ScenarioConfig:
        return from_dict(ScenarioConfig, {**to_dict(base), **kw}, source=str(file))

    rest = {k: v for k, v in given.items() if k not in ("file", "network")}
    extra = {k: v for k, v in overrides.items() if k not in ("file", "network")}
    return _config_from_kwargs(base.network, rest, preset=preset, **extra)
