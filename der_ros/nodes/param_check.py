"""Validation of one node's ROS parameters, ROS-free, with one error line per bad value.

Why a check of our own before rclpy sees the values: rclpy rejects a value outside a
parameter's descriptor range (or of another type) with an ``InvalidParameterValueException``
*traceback* from inside the node's constructor -- by then ``der graph`` has started the
recorder and the agent, and the run leaves an empty bag behind. So every value a node will be
given is checked here first, field by field with the same rules as the config files
(:func:`der_ros.configuration.check_value`: type, range, choices, finite floats), then section
by section (the dataclass's cross-field ``check()``), and a failure is one line::

    <origin>/<node>/<name> = <value>: <reason>

``origin`` is where the value came from: the params file, ``-p`` (``der graph -p``) or a
flag such as ``--lam``. ``der graph`` calls :func:`check_node_parameters` for every node
before any process starts; the node itself (:class:`der_ros.nodes.params.ConfigParameters`)
turns any value it is started with into the same line, and exits 1 without a traceback.
"""

from __future__ import annotations

import re
import typing
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from der_ros.configuration import (
    ConfigError,
    FieldSpec,
    check_value,
    field_specs,
    from_dict,
    to_dict,
    unflatten_names,
)
from der_ros.nodes.node_configs import NODE_SECTIONS, parameter_sections
from der_ros.replay.factory import check_replay_memory
from der_ros.replay.storage import ReplayMemoryError
from sumo_bridge.observation import empty_points, encode_observation

__all__ = [
    "ROS_OWN_PARAMETERS",
    "parameter_error",
    "node_field_specs",
    "check_parameter",
    "check_node_parameters",
    "section_error",
    "argv_origin",
]

#: parameters rclpy declares on every node by itself (booleans); all other names must be fields
ROS_OWN_PARAMETERS = ("use_sim_time", "start_type_description_service")

#: "name = value, expected ..." -- how the cross-field ``check()`` rules word their errors
_CHECK_MESSAGE = re.compile(r"^(?P<key>[\w.\[\]]+) = (?P<value>.*?), (?P<reason>expected .*)$", re.S)


def _show(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def parameter_error(origin: str, node: str, name: str, value: Any, reason: str) -> ConfigError:
    """The one-line error ``<origin>/<node>/<name> = <value>: <reason>``."""
    return ConfigError(f"{origin}/{node}/{name} = {_show(value)}: {reason}", key=name, value=value, reason=reason)


def node_field_specs(node: str) -> dict[str, FieldSpec]:
    """Parameter name -> field spec of every parameter ``node`` declares (nested sections flattened)."""
    return {name: spec for name, (spec, _prefix) in _owned_specs(node).items()}


def _owned_specs(node: str) -> dict[str, tuple[FieldSpec, str]]:
    """Parameter name -> (field spec, prefix of the section that declares it)."""
    out: dict[str, tuple[FieldSpec, str]] = {}

    def walk(obj: Any, name_prefix: str, section: str) -> None:
        for spec in field_specs(obj):
            name = f"{name_prefix}.{spec.name}" if name_prefix else spec.name
            if isinstance(spec.type, type) and hasattr(spec.type, "__dataclass_fields__"):
                walk(getattr(obj, spec.name), name, section)
            else:
                out[name] = (spec, section)

    for prefix, obj in parameter_sections(node).items():
        walk(obj, prefix, prefix)
    return out


def _ros_typed(spec: FieldSpec, value: Any) -> Any:
    """A checked value as rclpy must receive it: ROS parameters are statically typed, so an integer
    given for a float parameter (or inside a float list) becomes a float, tuples become lists."""
    if spec.type is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if typing.get_origin(spec.type) in (list, tuple) and isinstance(value, (list, tuple)):
        args = typing.get_args(spec.type)
        if args and args[0] is float:
            return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v for v in value]
        return list(value)
    return value


def check_parameter(node: str, name: str, value: Any, origin: str, specs: Mapping[str, FieldSpec] | None = None) -> Any:
    """One parameter value of ``node``, checked and typed for ROS; :class:`ConfigError` (one line) if bad."""
    if name in ROS_OWN_PARAMETERS:
        if not isinstance(value, bool):
            raise parameter_error(origin, node, name, value, "expected true or false")
        return value
    specs = node_field_specs(node) if specs is None else specs
    spec = specs.get(name)
    if spec is None:
        raise parameter_error(origin, node, name, value, f"{node} has no parameter {name!r}")
    if value is None and spec.nullable:
        return None
    try:
        checked = check_value(spec, value, source=origin)
    except ConfigError as exc:
        raise parameter_error(origin, node, name, value, exc.reason or str(exc)) from None
    return _ros_typed(spec, checked)


def check_node_parameters(node: str, values: Mapping[str, Any], origins: Mapping[str, str] | str) -> dict[str, Any]:
    """Every parameter ``node`` will be started with, checked as the node will check it.

    ``values`` are flat names (``replay.lam``); ``origins`` names where each came from (one
    origin for all, or name -> origin). Returns the values typed for ROS (null values of
    nullable fields dropped: the node's default is null). The cross-field rules of each section
    run on the defaults overlaid with ``values``. Raises :class:`ConfigError` with the one line
    of the first bad value.
    """
    if node not in NODE_SECTIONS:
        raise ConfigError(f"unknown node {node!r}; the graph's nodes are {', '.join(NODE_SECTIONS)}")

    def origin_of(name: str) -> str:
        return origins if isinstance(origins, str) else origins.get(name, "params")

    owned = _owned_specs(node)
    specs = {name: spec for name, (spec, _prefix) in owned.items()}
    typed: dict[str, Any] = {}
    for name, value in values.items():
        checked = check_parameter(node, name, value, origin_of(name), specs)
        if checked is not None:
            typed[name] = checked
    configs: dict[str, Any] = {}
    for prefix, default in parameter_sections(node).items():
        mine = {n: v for n, v in values.items() if n in owned and owned[n][1] == prefix and v is not None}
        try:
            configs[prefix] = from_dict(type(default), _merged(to_dict(default), unflatten_names(mine, prefix)),
                                        source="")
        except ConfigError as exc:
            raise section_error(node, prefix, exc, origin_of, mine) from None
    if node == "agent_node":
        _check_replay_fits(configs, origin_of("replay.capacity"))
    return typed


def _check_replay_fits(configs: Mapping[str, Any], origin: str) -> None:
    """The agent's replay must fit in memory (``replay.capacity: 1e12`` is a bad value, not a crash
    of the agent after the recorder started)."""
    agent, replay = configs["agent"], configs["replay"]
    if agent.batch_size > replay.capacity:
        raise parameter_error(origin, "agent_node", "agent.batch_size", agent.batch_size,
                              f"expected <= replay.capacity ({replay.capacity})")
    obs_shape = encode_observation(empty_points(), configs["observation"]).shape
    try:
        check_replay_memory(replay, obs_shape, np.float32, agent.batch_size)
    except ReplayMemoryError as exc:
        raise parameter_error(origin, "agent_node", "replay.capacity", replay.capacity, str(exc)) from None


def _merged(base: dict[str, Any], new: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``new`` laid over it, nested mappings merged key by key."""
    out = dict(base)
    for key, value in new.items():
        out[key] = _merged(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), dict) else value
    return out


def section_error(node: str, prefix: str, exc: ConfigError, origin_of: Any, values: Mapping[str, Any]) -> ConfigError:
    """A cross-field rule's error as the one line, naming the field the rule names."""
    text = str(exc).lstrip(": ").strip()
    match = _CHECK_MESSAGE.match(text.split(": ")[-1]) if exc.key is None else None
    if exc.key is not None:
        key, value, reason = exc.key, exc.value, exc.reason or text
    elif match is not None:
        key, value, reason = match["key"], match["value"], match["reason"]
    else:
        key, value, reason = "*", "", text
    name = f"{prefix}.{key}" if prefix else key
    origin = origin_of(name) if name in values else next((origin_of(n) for n in values), "defaults")
    if isinstance(value, str) and match is not None:
        return ConfigError(f"{origin}/{node}/{name} = {value}: {reason}", key=name, value=value, reason=reason)
    return parameter_error(origin, node, name, value, reason)


def argv_origin(name: str, argv: Sequence[str]) -> str:
    """Where a node's value of parameter ``name`` came from, read from its command line:
    ``-p`` if ``--ros-args -p name:=...`` sets it, else the ``--params-file`` (comma-joined if
    several), else ``--ros-args``."""
    files: list[str] = []
    from_p = False
    args = list(argv)
    for i, arg in enumerate(args[:-1]):
        nxt = args[i + 1]
        if arg in ("-p", "--param") and nxt.split(":=", 1)[0].rsplit(":", 1)[-1] == name:
            from_p = True
        elif arg == "--params-file":
            files.append(nxt)
    if from_p:
        return "-p"
    return ",".join(files) if files else "--ros-args"
