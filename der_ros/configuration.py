"""Typed configuration dataclasses: declaration, validation, YAML loading.

Every component has one frozen-free ``@dataclass`` config whose fields are declared with
:func:`param`, which records a help text and the allowed range/choices in the field's
metadata. The same metadata drives

* validation (:func:`validate`) with errors that name the field, the value and what was
  expected,
* YAML loading (:func:`load_yaml`, :func:`from_dict`) that rejects unknown keys and wrong
  types before any work starts, naming the file,
* CLI flags (:func:`add_dataclass_arguments`) and ROS parameter descriptors (the node
  adapters read :func:`field_specs`).

Nested dataclasses are allowed (a field whose type is another config dataclass).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import MISSING, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from der_ros import yaml_loader
from der_ros.yaml_loader import YamlError, excerpt

T = TypeVar("T")

__all__ = [
    "ConfigError",
    "FieldSpec",
    "param",
    "validate",
    "from_dict",
    "to_dict",
    "load_yaml",
    "read_yaml_mapping",
    "reject_unknown_keys",
    "save_yaml",
    "field_specs",
    "check_value",
    "INT64_MIN",
    "INT64_MAX",
    "add_dataclass_arguments",
    "apply_overrides",
    "flatten_names",
    "unflatten_names",
]


class ConfigError(ValueError):
    """A configuration value is invalid. The message names the source, the key and the value.

    Errors about one field also carry it structured (``key``, ``value``, ``reason``: what was
    expected), so callers that report in another layout -- ``der graph``'s one-line
    ``file/node/name = value: reason`` for node parameters -- need not parse the message.
    """

    def __init__(self, message: str, *, key: str | None = None, value: Any = None, reason: str | None = None) -> None:
        super().__init__(message)
        self.key = key
        self.value = value
        self.reason = reason


#: ROS 2 integer parameters and numpy index arrays are 64-bit: a larger integer is a mistake
#: (``capacity: 1e30``), never a setting.
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


@dataclass(frozen=True)
class FieldSpec:
    """What :func:`param` records about one config field."""

    name: str
    type: Any
    default: Any
    help: str
    low: float | None = None
    high: float | None = None
    low_inclusive: bool = True
    high_inclusive: bool = True
    choices: tuple[Any, ...] | None = None
    nullable: bool = False
    #: float fields are finite unless the field says that +-inf means something (``param(allow_inf=True)``)
    allow_inf: bool = False

    def describe_range(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        parts = []
        if self.low is not None:
            parts.append(f"{'>=' if self.low_inclusive else '>'} {self.low}")
        if self.high is not None:
            parts.append(f"{'<=' if self.high_inclusive else '<'} {self.high}")
        return " and ".join(parts) if parts else "any value"


def param(
    default: Any = MISSING,
    help: str = "",
    *,
    low: float | None = None,
    high: float | None = None,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
    choices: typing.Iterable[Any] | None = None,
    default_factory: Any = MISSING,
    allow_inf: bool = False,
) -> Any:
    """Declare a documented, range-checked config field.

    ``help`` becomes the CLI help and the ROS ``ParameterDescriptor.description``.
    ``low``/``high`` bound numeric values, ``choices`` restricts to a set. Float values must
    be finite (``lr: .inf`` passes ``low=0`` and crashes the first gradient step) unless
    ``allow_inf`` -- and the help text then says what infinity means.
    """
    if not help:
        raise TypeError("every config field needs a help text")
    meta = {
        "help": help,
        "low": low,
        "high": high,
        "low_inclusive": low_inclusive,
        "high_inclusive": high_inclusive,
        "choices": tuple(choices) if choices is not None else None,
        "allow_inf": allow_inf,
    }
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _resolved_hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        nullable = len(args) != len(typing.get_args(tp))
        if len(args) == 1:
            return args[0], nullable
        return typing.Union[tuple(args)], nullable  # noqa: UP007
    return tp, False


def field_specs(cls_or_obj: Any) -> list[FieldSpec]:
    """The :class:`FieldSpec` of every field of a config dataclass (not recursing)."""
    cls = cls_or_obj if isinstance(cls_or_obj, type) else type(cls_or_obj)
    hints = _resolved_hints(cls)
    out = []
    for f in fields(cls):
        tp, nullable = _unwrap_optional(hints[f.name])
        meta = f.metadata
        if f.default is not MISSING:
            default = f.default
        elif f.default_factory is not MISSING:
            default = f.default_factory()
        else:
            default = MISSING
        out.append(
            FieldSpec(
                name=f.name,
                type=tp,
                default=default,
                help=meta.get("help", ""),
                low=meta.get("low"),
                high=meta.get("high"),
                low_inclusive=meta.get("low_inclusive", True),
                high_inclusive=meta.get("high_inclusive", True),
                choices=meta.get("choices"),
                nullable=nullable,
                allow_inf=meta.get("allow_inf", False),
            )
        )
    return out


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _fail(where: str, spec: FieldSpec, value: Any, reason: str) -> ConfigError:
    return ConfigError(f"{where}: {spec.name} = {excerpt(value)}, {reason}", key=spec.name, value=value, reason=reason)


def _coerce(value: Any, spec: FieldSpec, where: str) -> Any:
    """Check (and minimally coerce: int -> float, list -> tuple) one value against its spec."""
    tp = spec.type
    if value is None:
        if spec.nullable:
            return None
        raise _fail(where, spec, None, f"expected {_type_name(tp)}")
    if is_dataclass(tp):
        if is_dataclass(value) and isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise _fail(where, spec, value, f"expected a mapping for {tp.__name__}")
        try:
            return from_dict(tp, value, source=f"{where}: {spec.name}")
        except ConfigError as exc:  # the key of a nested field is its dotted path
            key = f"{spec.name}.{exc.key}" if exc.key else None
            raise ConfigError(str(exc), key=key, value=exc.value, reason=exc.reason) from None
    origin = typing.get_origin(tp)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise _fail(where, spec, value, "expected a list")
        args = typing.get_args(tp)
        item_tp = args[0] if args else Any
        items = []
        for i, item in enumerate(value):
            if item_tp is not Any and item_tp is not Ellipsis:
                sub = dataclasses.replace(spec, name=f"{spec.name}[{i}]", type=item_tp, choices=None)
                item = _coerce(item, sub, where)
            items.append(item)
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(where, spec, value, "expected true or false")
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if not (isinstance(value, float) and value.is_integer()):
                raise _fail(where, spec, value, "expected an integer")
            if not INT64_MIN <= value < 2.0**63:
                raise _fail(where, spec, value, "expected an integer that fits in 64 bits")
            value = int(value)
        if not INT64_MIN <= value <= INT64_MAX:
            raise _fail(where, spec, value, "expected an integer that fits in 64 bits")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(where, spec, value, "expected a number")
        value = float(value)
        if math.isnan(value) or (math.isinf(value) and not spec.allow_inf):
            raise _fail(where, spec, value, "expected a finite number")
    elif tp is str:
        if not isinstance(value, str):
            raise _fail(where, spec, value, "expected a string")
    if spec.choices is not None and value not in spec.choices:
        raise _fail(where, spec, value, f"expected {spec.describe_range()}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        bad = False
        if spec.low is not None:
            bad |= value < spec.low if spec.low_inclusive else value <= spec.low
        if spec.high is not None:
            bad |= value > spec.high if spec.high_inclusive else value >= spec.high
        if bad:
            raise _fail(where, spec, value, f"expected {spec.describe_range()}")
    return value


def check_value(spec: FieldSpec, value: Any, source: str = "config") -> Any:
    """One value checked (and coerced) against a field's spec; :class:`ConfigError` with
    ``key``/``value``/``reason`` set if it does not fit (used for single ROS parameters)."""
    return _coerce(value, spec, source)


def validate(obj: Any, source: str = "config") -> Any:
    """Check every field of ``obj`` (recursively) in place; returns ``obj``.

    Calls ``obj.check()`` afterwards if the class defines it (for cross-field rules).
    """
    for spec in field_specs(obj):
        value = getattr(obj, spec.name)
        setattr(obj, spec.name, _coerce(value, spec, source))
    check = getattr(obj, "check", None)
    if callable(check):
        try:
            check()
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}", key=exc.key, value=exc.value, reason=exc.reason) from None
    return obj


def reject_unknown_keys(
    data: Mapping[str, Any], known: Iterable[str], source: str, what: str = "key", known_as: str = "known keys"
) -> None:
    """Raise :class:`ConfigError` for the first (sorted) key of ``data`` not in ``known``.

    The message names the source, the key, its value and the known keys (in the order given):
    ``"<source>: unknown <what> 'k' (value v); <known_as>: a, b"``.
    """
    known = list(known)
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(
            f"{source}: unknown {what} {excerpt(unknown[0])} (value {excerpt(data[unknown[0]])}); {known_as}: "
            f"{', '.join(known)}"
        )


def from_dict(cls: type[T], data: dict[str, Any] | None, source: str = "config") -> T:
    """Build and validate a config dataclass from a mapping; unknown keys are errors."""
    data = dict(data or {})
    specs = {s.name: s for s in field_specs(cls)}
    reject_unknown_keys(data, sorted(specs), source, what="key", known_as=f"known keys of {cls.__name__}")
    kwargs = {}
    for name, spec in specs.items():
        if name in data:
            kwargs[name] = _coerce(data[name], spec, source)
        elif spec.default is MISSING:
            raise ConfigError(f"{source}: required key {name!r} is missing")
    obj = cls(**kwargs)
    return validate(obj, source)


def to_dict(obj: Any) -> dict[str, Any]:
    """A plain (YAML-safe) dict of a config dataclass, recursively."""
    out: dict[str, Any] = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if is_dataclass(v):
            v = to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


def read_yaml_mapping(path: str | Path, expected: str = "a mapping") -> dict[str, Any]:
    """The top-level mapping of a YAML file; :class:`ConfigError` naming the file if it is missing,
    not text (binary garbage: the first byte that is not UTF-8), not valid YAML, empty or only
    comments (an empty file would silently mean "all defaults", which is never what its author
    meant; write ``{}`` for that), or not ``expected`` (a mapping) at the top level. Read with
    :func:`der_ros.yaml_loader.load_yaml`: duplicate keys, too deep or too large files and
    ambiguous scalars are refused, numbers follow YAML 1.2 (``1e-3`` is a float)."""
    path = Path(path)
    try:
        data = yaml_loader.load_yaml(path)
    except YamlError as exc:
        raise ConfigError(str(exc), key=exc.key) from None
    if data is None:
        raise ConfigError(f"{path}: the file is empty or holds only comments; expected {expected} (write {{}} "
                          "to use every default)")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected {expected} at the top level, got {type(data).__name__}")
    return data


def load_yaml(path: str | Path, cls: type[T], section: str | None = None) -> T:
    """Load ``cls`` from a YAML file (optionally from one top-level ``section`` of it)."""
    path = Path(path)
    data = read_yaml_mapping(path)
    source = str(path)
    if section is not None:
        data = data.get(section, {})
        source = f"{path} [{section}]"
    return from_dict(cls, data, source=source)


def save_yaml(obj: Any, path: str | Path) -> None:
    """Write a config dataclass as YAML (atomically)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(yaml.safe_dump(to_dict(obj), sort_keys=False))
    tmp.replace(path)


def _flag_type(spec: FieldSpec) -> Any:
    if spec.type is bool:
        return lambda s: {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}[s.lower()]
    if spec.type in (int, float, str):
        return spec.type
    return None


def add_dataclass_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add one ``--prefix-field`` flag per scalar field (default None = keep the config's value)."""
    for spec in field_specs(cls):
        conv = _flag_type(spec)
        if conv is None:
            continue
        flag = "--" + (prefix + spec.name).replace("_", "-")
        parser.add_argument(
            flag,
            dest=(prefix + spec.name),
            type=conv,
            default=None,
            help=f"{spec.help} ({spec.describe_range()})",
        )


def apply_overrides(obj: T, overrides: dict[str, Any], source: str = "command line") -> T:
    """Return a validated copy of ``obj`` with the non-None ``overrides`` applied."""
    data = to_dict(obj)
    names = {s.name for s in field_specs(obj)}
    for k, v in overrides.items():
        if v is None:
            continue
        if k not in names:
            raise ConfigError(f"{source}: unknown key {k!r}")
        data[k] = v
    return from_dict(type(obj), data, source=source)


def flatten_names(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings as dotted names: ``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (``prefix.a.b`` with a prefix).

    The one spelling of config paths shared by ROS parameters (``agent.lr``,
    ``scenario.observation.speed_scale``), params files and ``--set``/``-p`` overrides.
    """
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten_names(value, name))
        else:
            out[name] = value
    return out


def unflatten_names(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Inverse of :func:`flatten_names`: dotted names -> nested mappings. With ``prefix``, only the
    names under it are taken, without the prefix (``{"agent.lr": 1e-3, "seed": 1}``, ``"agent"``
    -> ``{"lr": 1e-3}``)."""
    out: dict[str, Any] = {}
    head = prefix + "." if prefix else ""
    for name, value in values.items():
        if not name.startswith(head):
            continue
        parts = name[len(head):].split(".")
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out
