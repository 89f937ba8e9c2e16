"""Config dataclasses as ROS 2 node parameters: declare, read back, validate on set.

One ROS parameter per leaf field of a config dataclass (see :mod:`der_ros.configuration`).
A *section* maps a name prefix to a config object: section ``"agent"`` with a
:class:`~der_ros.agent.config.DQNConfig` gives ``agent.lr``, ``agent.gamma``...; a nested
dataclass field adds another level (``scenario.observation.speed_scale``); the empty prefix
``""`` gives top-level names (``mode``, ``max_steps``).

Each parameter gets a :class:`rcl_interfaces.msg.ParameterDescriptor` built from the field's
``param(...)`` metadata: the help text as description, ``FloatingPointRange`` /
``IntegerRange`` from ``low``/``high``, the choices or exclusive bounds as
``additional_constraints``, and ``read_only`` for every parameter the node did not list as
mutable (changing a replay capacity or a network size under a running learner makes no sense,
so the default is read-only).

A set-parameters request is validated *before* it is applied: the candidate section is rebuilt
with :func:`der_ros.configuration.from_dict` (field ranges, choices and the dataclass's
cross-field ``check()``), and a :class:`~der_ros.configuration.ConfigError` turns into
``SetParametersResult(successful=False, reason=...)``, so the node keeps its old value and the
caller learns why.

Public API (used by the agent, bridge and recorder nodes)::

    bound = ConfigParameters(node, {"agent": DQNConfig(), "replay": ReplayConfig()},
                             mutable={"replay.lam"}, on_change=callback)
    bound.get("agent")          # the validated DQNConfig built from the node's parameters
    flat_parameters("agent", DQNConfig())   # {"agent.lr": 0.0005, ...} (ROS-free; YAML tooling)

and, ROS-free, the assembly of a graph's params file from a base file, the run's choices and
``NODE:NAME=VALUE`` overrides (:func:`build_graph_params`, used by ``der graph``): every value is
typed by the parameter it sets, and an unknown node or parameter is a :class:`ConfigError`
before any process starts.
"""

from __future__ import annotations

import array
import copy
import math
import sys
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import is_dataclass
from pathlib import Path
from typing import Any

from der_ros.configuration import (
    ConfigError,
    FieldSpec,
    field_specs,
    flatten_names,
    from_dict,
    read_yaml_mapping,
    to_dict,
    unflatten_names,
)
from der_ros.contract import COMMAND, STATE, default_record_topics
from der_ros.nodes.node_configs import NODE_SECTIONS
from der_ros.nodes.param_check import (
    argv_origin,
    check_node_parameters,
    check_parameter,
    parameter_error,
    section_error,
)
from der_ros.safety.config import FLEET_FIELDS, SafetyConfig
from der_ros.yaml_loader import YamlError, excerpt, load_yaml_text
from sumo_bridge.network_build import NETWORK_NAMES
from sumo_bridge.scenario_file import load_scenario, load_scenario_config

__all__ = [
    "ConfigParameters",
    "ChangeCallback",
    "flat_parameters",
    "flat_specs",
    "params_file_section",
    "load_params_file",
    "parse_overrides",
    "build_graph_params",
]

#: ``on_change(section, new_config, changed_parameter_names)``, called after a set succeeded.
ChangeCallback = Callable[[str, Any, list[str]], None]

_INT64_MAX = 2**63 - 1


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def flat_specs(cls_or_obj: Any, prefix: str = "") -> dict[str, FieldSpec]:
    """Parameter name -> :class:`FieldSpec` of every leaf field (nested dataclasses flattened)."""
    out: dict[str, FieldSpec] = {}
    for spec in field_specs(cls_or_obj):
        name = _join(prefix, spec.name)
        if is_dataclass(spec.type):
            sub = getattr(cls_or_obj, spec.name) if not isinstance(cls_or_obj, type) else spec.type
            out.update(flat_specs(sub, name))
        else:
            out[name] = spec
    return out


def flat_parameters(prefix: str, obj: Any) -> dict[str, Any]:
    """Parameter name -> value of every leaf field of a config object (tuples become lists)."""
    return flatten_names(to_dict(obj), prefix)


def params_file_section(sections: Mapping[str, Any], extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``{"ros__parameters": {...}}`` of a node for a ROS params YAML file, from its sections.

    Values that a params file cannot carry (``None``, empty lists: rcl's YAML parser has no type
    for them) are left out; the node's declared defaults then apply.
    """
    flat: dict[str, Any] = {}
    for prefix, obj in sections.items():
        for name, value in flat_parameters(prefix, obj).items():
            if value is None or (isinstance(value, list) and not value):
                continue
            flat[name] = value
    flat.update(extra or {})
    return {"ros__parameters": flat}


def _ros_value(value: Any) -> Any:
    """A value rclpy can store (lists for sequences; everything else unchanged)."""
    if isinstance(value, tuple):
        return list(value)
    return value


def _python_value(value: Any) -> Any:
    """A parameter value as plain Python (rclpy returns ``array.array`` for numeric arrays)."""
    if isinstance(value, array.array):
        return value.tolist()
    return value


def _descriptor(name: str, spec: FieldSpec, read_only: bool, default: Any) -> Any:
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

    desc = ParameterDescriptor(name=name, description=spec.help, read_only=read_only)
    constraints = []
    if spec.choices is not None:
        constraints.append(spec.describe_range())
    elif spec.low is not None or spec.high is not None:
        if not (spec.low_inclusive and spec.high_inclusive):
            constraints.append(spec.describe_range())
        if spec.type is float:
            low = -math.inf if spec.low is None else float(spec.low)
            high = math.inf if spec.high is None else float(spec.high)
            desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
        elif spec.type is int:
            low_i = -_INT64_MAX - 1 if spec.low is None else math.ceil(spec.low)
            high_i = _INT64_MAX if spec.high is None else math.floor(spec.high)
            desc.integer_range = [IntegerRange(from_value=low_i, to_value=high_i, step=1)]
    if spec.nullable:
        constraints.append("may be unset (null)")
        desc.dynamic_typing = True
    if isinstance(default, (list, tuple)) and len(default) == 0:
        # rclpy infers BYTE_ARRAY for [], which would then refuse a string list: let the
        # dataclass validation (on set) check the element type instead.
        desc.dynamic_typing = True
    desc.additional_constraints = "; ".join(constraints)
    type_map = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
                float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
    if spec.type in type_map:
        desc.type = type_map[spec.type]
    elif typing.get_origin(spec.type) in (list, tuple):
        args = typing.get_args(spec.type)
        item = args[0] if args else None
        desc.type = {
            bool: ParameterType.PARAMETER_BOOL_ARRAY,
            int: ParameterType.PARAMETER_INTEGER_ARRAY,
            float: ParameterType.PARAMETER_DOUBLE_ARRAY,
            str: ParameterType.PARAMETER_STRING_ARRAY,
        }.get(item, ParameterType.PARAMETER_NOT_SET)
    return desc


class ConfigParameters:
    """Binds config sections to a node's parameters (declare, read back, validate, notify).

    ``sections`` maps a prefix to a config object whose values are the defaults (values in the
    node's params file override them, as usual in ROS). ``mutable`` lists the full parameter
    names that may change while the node runs (every other one is declared ``read_only``); the
    node applies those changes in ``on_change``. Raises :class:`ConfigError` when the values
    given at start-up do not validate.
    """

    def __init__(
        self,
        node: Any,
        sections: Mapping[str, Any],
        *,
        mutable: Iterable[str] = (),
        on_change: ChangeCallback | None = None,
    ) -> None:

        from rclpy.exceptions import ParameterException

        self._node = node
        self._types = {prefix: type(obj) for prefix, obj in sections.items()}
        self._specs: dict[str, dict[str, FieldSpec]] = {}
        self._owner: dict[str, str] = {}
        self._on_change = on_change
        mutable = set(mutable)
        node_name = node.get_name()
        all_specs = {name: spec for prefix, obj in sections.items() for name, spec in flat_specs(obj, prefix).items()}
        # The values the node is started with (params file, -p) are checked before rclpy sees them, so a
        # bad one is the one line of der_ros.nodes.param_check instead of an rclpy traceback.
        overrides = {name: _python_value(p.value) for name, p in getattr(node, "_parameter_overrides", {}).items()}
        for name, value in overrides.items():
            if name in all_specs:
                check_parameter(node_name, name, value, argv_origin(name, sys.argv), all_specs)
        for prefix, obj in sections.items():
            specs = flat_specs(obj, prefix)
            self._specs[prefix] = specs
            values = flat_parameters(prefix, obj)
            for name, spec in specs.items():
                if name in self._owner:
                    raise ValueError(f"parameter {name!r} declared by two sections")
                self._owner[name] = prefix
                desc = _descriptor(name, spec, read_only=name not in mutable, default=values[name])
                value = _ros_value(values[name])
                try:
                    node.declare_parameter(name, value, desc)  # None: dynamic_typing is set for nullable fields
                except ParameterException as exc:  # what our check cannot see (e.g. 1 for a double parameter)
                    given = overrides.get(name, value)
                    if spec.type is float and isinstance(given, int) and not isinstance(given, bool):
                        reason = f"expected a floating-point number (a ROS double parameter: write {float(given)!r})"
                    else:
                        reason = " ".join(str(exc).split()) or type(exc).__name__
                    raise parameter_error(argv_origin(name, sys.argv), node_name, name, given, reason) from None
        missing = mutable.difference(self._owner)
        if missing:
            raise ValueError(f"mutable parameters {sorted(missing)} are not fields of any section")
        self._current: dict[str, Any] = {}
        for prefix in sections:
            try:
                self._current[prefix] = self._build(prefix, {}, source="")
            except ConfigError as exc:  # a cross-field rule
                given = {n: overrides[n] for n in self._specs[prefix] if n in overrides}
                raise section_error(node_name, prefix, exc, lambda n: argv_origin(n, sys.argv), given) from None
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._applied)

    # -- reading -------------------------------------------------------------------------------
    def get(self, section: str) -> Any:
        """The current, validated config object of ``section`` (a fresh copy)."""
        return copy.deepcopy(self._current[section])

    @property
    def names(self) -> list[str]:
        """Every parameter name this binding declared."""
        return sorted(self._owner)

    def _value(self, name: str) -> Any:
        return _python_value(self._node.get_parameter(name).value)

    def _build(self, prefix: str, overrides: Mapping[str, Any], source: str) -> Any:
        values = {name: overrides[name] if name in overrides else self._value(name) for name in self._specs[prefix]}
        return from_dict(self._types[prefix], unflatten_names(values, prefix), source=source)

    # -- set-parameters callbacks ----------------------------------------------------------------
    def _by_section(self, params: Iterable[Any]) -> dict[str, dict[str, Any]]:
        grouped: dict[str, dict[str, Any]] = {}
        for p in params:
            prefix = self._owner.get(p.name)
            if prefix is not None:
                grouped.setdefault(prefix, {})[p.name] = _python_value(p.value)
        return grouped

    def _validate(self, params: list[Any]) -> Any:
        from rcl_interfaces.msg import SetParametersResult

        for prefix, new in self._by_section(params).items():
            try:
                self._build(prefix, new, source="set_parameters")
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            except (TypeError, ValueError) as exc:  # e.g. a value the dataclass cannot hold
                return SetParametersResult(successful=False, reason=f"set_parameters: {exc}")
        return SetParametersResult(successful=True)

    def _applied(self, params: list[Any]) -> None:
        for prefix, new in self._by_section(params).items():
            self._current[prefix] = self._build(prefix, {}, source="set_parameters")
            if self._on_change is not None:
                self._on_change(prefix, self.get(prefix), sorted(new))


# -- a graph's params file (ROS-free) ----------------------------------------------------------------
def load_params_file(path: str | Path | None) -> dict[str, Any]:
    """A ROS params YAML (node name -> ``{ros__parameters: ...}``); {} for None."""
    if path is None:
        return {}
    return read_yaml_mapping(path, expected="a mapping of node names")


def parse_overrides(items: Iterable[str]) -> dict[str, dict[str, Any]]:
    """``NODE:NAME=VALUE`` items (value parsed as YAML) -> node -> name -> value."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        node, sep, rest = item.partition(":")
        name, eq, value = rest.partition("=")
        if not sep or not eq or node not in NODE_SECTIONS or not name:
            raise ConfigError(f"-p {item!r}: expected NODE:NAME=VALUE with NODE in {', '.join(NODE_SECTIONS)}")
        try:
            out.setdefault(node, {})[name] = load_yaml_text(value, f"-p {node}:{name}")
        except YamlError as exc:
            if not exc.syntax:  # YAML that says something ambiguous, too deep or too large
                raise ConfigError(str(exc), key=name) from None
            out.setdefault(node, {})[name] = value  # not YAML: the text itself (the check names the type)
    return out


def build_graph_params(
    base: Mapping[str, Any],
    *,
    steps: int,
    scenario: str,
    run_dir: Path,
    free_run: bool = False,
    replay: str | None = None,
    lam: float | None = None,
    seed: int | None = None,
    overrides: Iterable[str] = (),
    base_name: str = "params file",
    safety: str = "none",
) -> dict[str, Any]:
    """The params file of one ``der graph`` run: ``base`` plus the run's choices plus ``-p`` overrides.

    Parameters are written with flat dotted names so a choice replaces the file's value whether
    the file nested it or not. Outputs go to ``run_dir`` (``agent.pt``, ``bag``). When the recorder
    records ``state``, the bridge waits for two subscribers (agent and recorder) before its first
    step, unless told otherwise: a short fast run could otherwise finish before the recorder matched.

    Every value of the three nodes is then checked as the node will check it
    (:func:`der_ros.nodes.param_check.check_node_parameters`) and typed for ROS; a bad one is a
    :class:`ConfigError` of one line naming where it came from (``base_name``, ``-p``, ``--lam``...).
    """
    params = copy.deepcopy(dict(base))
    origins: dict[str, dict[str, str]] = {}
    for node in params:  # a ROS params file: node name -> {ros__parameters: ...}, nothing else (rcl refuses it)
        if node not in NODE_SECTIONS:
            raise ConfigError(f"{base_name}: top-level key {excerpt(node)} is not a node of the graph; a ROS params "
                              f"file maps {', '.join(NODE_SECTIONS)} to {{ros__parameters: ...}}")
        section = params[node]
        if not isinstance(section, dict) or set(section) != {"ros__parameters"}:
            found = ", ".join(excerpt(k) for k in section) if isinstance(section, dict) else type(section).__name__
            raise ConfigError(f"{base_name}: section {node!r} is not a ROS params section: expected exactly the key "
                              f"ros__parameters, found {found or 'nothing'}")
    for node in NODE_SECTIONS:
        section = params.setdefault(node, {})
        if not isinstance(section, dict) or not isinstance(section.get("ros__parameters", {}), dict):
            raise ConfigError(f"{base_name}: section {node!r} is not a mapping with ros__parameters")
        section["ros__parameters"] = flatten_names(section.get("ros__parameters") or {})
        origins[node] = dict.fromkeys(section["ros__parameters"], base_name)

    def put(node: str, name: str, value: Any, origin: str) -> None:
        params[node]["ros__parameters"][name] = value
        origins[node][name] = origin

    put("bridge_node", "max_steps", int(steps), "--steps")
    put("bridge_node", "scenario.network", scenario, "--scenario")
    if scenario not in NETWORK_NAMES:  # a scenario file: its fields become the bridge's scenario.* parameters
        for name, value in flatten_names(to_dict(load_scenario_config(scenario))).items():  # the file wins over base
            if isinstance(value, (list, tuple)) and not value:
                continue  # ROS cannot type an empty array: the node's default (empty) stays
            put("bridge_node", f"scenario.{name}", list(value) if isinstance(value, tuple) else value, "--scenario")
        file_cfg = load_scenario_config(scenario)
        put("agent_node", "n_actions", len(file_cfg.actions), "--scenario")
        put("safety_node", "n_actions", len(file_cfg.actions), "--scenario")
        for name, value in flatten_names(to_dict(file_cfg.observation)).items():  # the agent encodes the same way
            put("agent_node", f"observation.{name}", value, "--scenario")
        shield = params["safety_node"]["ros__parameters"]
        for name, value in load_scenario(file_cfg.file).safety.items():  # the fleet's worst case: the cautious value
            mine = float(shield.get(f"safety.{name}", getattr(SafetyConfig(), name)))
            if (value > mine) if FLEET_FIELDS[name] else (value < mine):
                put("safety_node", f"safety.{name}", value, "--scenario")
    if free_run:
        put("bridge_node", "mode", "free_run", "--free-run")
    if replay is not None:
        put("agent_node", "replay.kind", replay, "--replay")
    if lam is not None:
        put("agent_node", "replay.lam", lam, "--lam")
    if seed is not None:
        put("agent_node", "seed", seed, "--seed")
        put("bridge_node", "scenario.seed", seed, "--seed")
    put("agent_node", "checkpoint_out", str(run_dir / "agent.pt"), "--run-dir")
    put("recorder_node", "output", str(run_dir / "bag"), "--run-dir")
    if safety != "none":
        put("safety_node", "safety.kind", safety, "--safety")
    extra = parse_overrides(overrides)
    for node, values in extra.items():
        for name, value in values.items():
            put(node, name, value, "-p")
    rec = params["recorder_node"]["ros__parameters"]
    records_state = rec.get("all_topics") or STATE in [
        str(t).lstrip("/") for t in rec.get("topics", default_record_topics()) if isinstance(t, str)]
    if records_state and "min_subscribers" not in extra.get("bridge_node", {}):
        put("bridge_node", "min_subscribers", 2, "der graph")
    records_commands = rec.get("all_topics") or COMMAND in [
        str(t).lstrip("/") for t in rec.get("topics", default_record_topics()) if isinstance(t, str)]
    if records_commands and "min_command_subscribers" not in extra.get("agent_node", {}):
        put("agent_node", "min_command_subscribers", 1, "der graph")
    for node in NODE_SECTIONS:  # every value as the node will check it: one line, before any process starts
        params[node]["ros__parameters"] = check_node_parameters(node, params[node]["ros__parameters"], origins[node])
    return params
