"""The one YAML loader of the project: files that cannot lie.

Every YAML the project reads -- training configs, ROS params files, ``config/baselines.yaml``,
scenario files, bag ``metadata.yaml``, values given on the command line -- goes through
:func:`load_yaml` (a file) or :func:`load_yaml_text` (a string). PyYAML's ``safe_load`` alone
accepts files that say something other than what their author meant; this loader refuses them
with :class:`YamlError`, one short line naming the file, the line and the key:

* a **duplicate key** at any depth (PyYAML keeps the last one silently: a second ``agent:``
  section replaced the whole first one) -> ``line 9: key 'agent': duplicate key (first at line 2)``;
* nesting deeper than ``max_depth`` (PyYAML's composer recurses and ends in ``RecursionError``),
  a file larger than ``max_bytes``, a scalar longer than ``max_scalar`` characters;
* a plain scalar that YAML 1.1 and YAML 1.2 read differently (``yes``/``no``/``on``/``off``,
  ``017``, ``1_000``, ``1:30``, ``0b101``): quote it or write it the unambiguous way.

Scalars are resolved with the **YAML 1.2 core schema**: ``1e-3`` and ``.5`` are floats (YAML 1.1
makes ``1e-3`` a string), ``0o17`` and ``0x1F`` are ints, ``true``/``false`` (any case variant of
the spec) are booleans, ``null``/``~``/empty are None, anything else is a string (no timestamps).
Errors quote at most :data:`EXCERPT` characters of any value (:func:`excerpt`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, ScalarNode, SequenceNode

__all__ = ["MAX_BYTES", "MAX_DEPTH", "MAX_SCALAR", "EXCERPT", "YamlError", "excerpt", "load_yaml", "load_yaml_text"]

#: largest file read (a config or params file is a few kB; a bag's metadata.yaml tens of kB)
MAX_BYTES = 1 << 20
#: deepest nesting of mappings and sequences (our deepest file nests 4 levels)
MAX_DEPTH = 64
#: longest scalar (characters)
MAX_SCALAR = 1 << 16
#: longest excerpt of a value quoted in an error message (characters)
EXCERPT = 40


class YamlError(ValueError):
    """A YAML file or text was refused; the message is one short line naming source, line and key."""

    def __init__(self, message: str, *, source: str = "", line: int | None = None, key: str | None = None,
                 syntax: bool = False) -> None:
        super().__init__(message)
        self.source = source
        self.line = line
        self.key = key
        #: the text is not YAML at all (a scanner/parser error), as opposed to YAML that was refused
        self.syntax = syntax


def excerpt(value: Any, limit: int = EXCERPT) -> str:
    """``repr(value)``, cut to ``limit`` characters with the full length named (for error messages)."""
    text = repr(value)
    if len(text) <= limit:
        return text
    size = len(value) if isinstance(value, (str, bytes, list, tuple, dict)) else len(text)
    return f"{text[:limit]}... ({size} characters)" if isinstance(value, (str, bytes)) else f"{text[:limit]}... "


# -- YAML 1.2 core schema ----------------------------------------------------------------------------
_INT = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_FLOAT = re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_NULL = re.compile(r"^(?:~|null|Null|NULL|)$")
#: plain scalars YAML 1.1 reads as something else than YAML 1.2 does (bool, octal, base 60, _ digits)
_AMBIGUOUS = re.compile(
    r"^(?:y|Y|yes|Yes|YES|n|N|no|No|NO|on|On|ON|off|Off|OFF"
    r"|[-+]?0[0-9_]+"  # 1.1 octal (or a string), 1.2 decimal
    r"|[-+]?0b[01_]+"  # 1.1 binary, 1.2 string
    r"|[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?"  # 1.1 base 60, 1.2 string
    r"|[-+]?(?:[0-9][0-9_]*)?\.?[0-9_]*_[0-9_]*(?:[eE][-+]?[0-9]+)?"  # 1.1 number with _, 1.2 string
    r"|[-+]?0x[0-9a-fA-F_]*_[0-9a-fA-F_]*"
    r")$"
)
_TAG = "tag:yaml.org,2002:"


class _Loader(yaml.SafeLoader):
    """SafeLoader with the YAML 1.2 core schema and the checks of this module."""

    yaml_implicit_resolvers: dict = {}  # replaced below (the 1.1 resolvers of SafeLoader are not inherited)

    def __init__(self, stream: str, source: str, max_depth: int, max_scalar: int) -> None:
        super().__init__(stream)
        self.source = source
        self.max_depth = max_depth
        self.max_scalar = max_scalar
        self._depth = 0
        self._path: list[str] = []

    def fail(self, line: int | None, what: str, key: str | None = None) -> YamlError:
        key = key if key is not None else self.key_path()
        where = f"{self.source}: line {line}" if line is not None else self.source
        return YamlError(f"{where}: key {key!r}: {what}" if key else f"{where}: {what}", source=self.source,
                         line=line, key=key)

    def key_path(self, extra: str | None = None) -> str:
        parts = [*self._path, extra] if extra is not None else list(self._path)
        if len(parts) > 6:
            parts = [*parts[:3], "...", *parts[-2:]]
        out = ""
        for part in parts:  # a.b[0].c, shortened to a.b.c...y.z
            out += part if part.startswith("[") or part == "..." or not out or out.endswith("...") else "." + part
        return out

    def compose_node(self, parent: Any, index: Any) -> Any:  # noqa: D401 - PyYAML hook
        is_key = isinstance(parent, MappingNode) and index is None
        if isinstance(index, ScalarNode):
            self._path.append(excerpt(index.value, 20) if len(index.value) > 20 else index.value)
        elif isinstance(index, int):
            self._path.append(f"[{index}]")
        elif parent is not None and not is_key:
            self._path.append("?")
        pushed = parent is not None and not is_key
        self._depth += 1
        try:
            if self._depth > self.max_depth and not self.check_event(yaml.AliasEvent):
                event = self.peek_event()
                if not isinstance(event, yaml.ScalarEvent):
                    raise self.fail(event.start_mark.line + 1, f"nested deeper than {self.max_depth} levels")
            node = super().compose_node(parent, index)
            if isinstance(node, ScalarNode):
                self._check_scalar(node, is_key)
        finally:
            self._depth -= 1
            if pushed:
                self._path.pop()
        return node

    def compose_sequence_node(self, anchor: Any) -> Any:
        # PyYAML passes no index for sequence items; count them so errors can name "key[3]"
        start_event = self.get_event()
        tag = start_event.tag
        if tag is None or tag == "!":
            tag = self.resolve(SequenceNode, None, start_event.implicit)
        node = SequenceNode(tag, [], start_event.start_mark, None, flow_style=start_event.flow_style)
        if anchor is not None:
            self.anchors[anchor] = node
        index = 0
        while not self.check_event(yaml.SequenceEndEvent):
            node.value.append(self.compose_node(node, index))
            index += 1
        node.end_mark = self.get_event().end_mark
        return node

    def compose_mapping_node(self, anchor: Any) -> Any:
        node = super().compose_mapping_node(anchor)
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, ScalarNode) or key_node.tag == _TAG + "merge":
                continue
            key = self.construct_object(key_node)
            canon = key  # what a Python dict would merge (1, 1.0 and true are one key)
            line = key_node.start_mark.line + 1
            if canon in seen:
                shown = key_node.value if len(key_node.value) <= EXCERPT else excerpt(key_node.value)
                raise self.fail(line, f"duplicate key (first at line {seen[canon]})", key=self.key_path(shown))
            seen[canon] = line
        return node

    def _check_scalar(self, node: ScalarNode, is_key: bool) -> None:
        line = node.start_mark.line + 1
        if len(node.value) > self.max_scalar:
            raise self.fail(line, f"a value of {len(node.value)} characters ({excerpt(node.value)}), more than "
                                  f"{self.max_scalar}")
        if node.tag == _TAG + "int" and len(node.value) > 4000:
            raise self.fail(line, f"an integer of {len(node.value)} digits; expected a number a program can use")
        if (node.tag == _TAG + "float" and not node.value.lower().endswith((".inf", ".nan"))
                and math.isinf(float(node.value))):
            raise self.fail(line, f"{excerpt(node.value)} is beyond the float range (it would be read as inf)")
        if not is_key and node.style is None and _AMBIGUOUS.match(node.value):
            raise self.fail(line, f"{excerpt(node.value)} means something else in YAML 1.1 than in YAML 1.2; quote "
                                  "it, or write true/false or a plain decimal number")


def _construct_int(loader: yaml.SafeLoader, node: ScalarNode) -> int:
    value = loader.construct_scalar(node)
    if value.startswith("0o"):
        return int(value[2:], 8)
    if value.startswith("0x"):
        return int(value[2:], 16)
    return int(value, 10)


def _construct_float(loader: yaml.SafeLoader, node: ScalarNode) -> float:
    value = loader.construct_scalar(node).lower()
    if value.endswith(".inf"):
        return -math.inf if value.startswith("-") else math.inf
    if value == ".nan":
        return math.nan
    return float(value)


def _construct_bool(loader: yaml.SafeLoader, node: ScalarNode) -> bool:
    return loader.construct_scalar(node).lower() == "true"


_Loader.yaml_implicit_resolvers = {}
for _tag, _regexp, _first in (
    ("bool", _BOOL, "tTfF"),
    ("null", _NULL, ["~", "n", "N", ""]),
    ("int", _INT, "-+0123456789"),
    ("float", _FLOAT, "-+.0123456789"),
):
    _Loader.add_implicit_resolver(_TAG + _tag, _regexp, list(_first))
_Loader.add_implicit_resolver(_TAG + "merge", re.compile(r"^(?:<<)$"), ["<"])
_Loader.add_constructor(_TAG + "int", _construct_int)
_Loader.add_constructor(_TAG + "float", _construct_float)
_Loader.add_constructor(_TAG + "bool", _construct_bool)


def load_yaml_text(text: str, source: str = "<text>", *, max_depth: int = MAX_DEPTH, max_scalar: int = MAX_SCALAR) -> Any:
    """Parse one YAML document from ``text`` (``source`` names it in errors); YamlError if refused."""
    loader = _Loader(text, source, max_depth, max_scalar)
    try:
        return loader.get_single_data()
    except YamlError:
        raise
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = " ".join(str(exc.problem or exc.context or "unreadable").split())[:80]
        err = loader.fail(line, f"not valid YAML: {problem}", key=loader.key_path() or None)
        err.syntax = True
        raise err from None
    except yaml.YAMLError as exc:
        err = loader.fail(None, f"not valid YAML: {' '.join(str(exc).split())[:80]}", key=None)
        err.syntax = True
        raise err from None
    except (ValueError, OverflowError) as exc:  # a constructor refused a scalar
        raise loader.fail(None, f"unreadable value: {' '.join(str(exc).split())[:80]}", key=None) from None
    finally:
        loader.dispose()


def load_yaml(path: str | Path, *, max_bytes: int = MAX_BYTES, max_depth: int = MAX_DEPTH,
              max_scalar: int = MAX_SCALAR) -> Any:
    """Parse the YAML file at ``path`` (None if it is empty or only comments); YamlError naming the
    file if it is missing, too large, not UTF-8 text, or refused by :func:`load_yaml_text`."""
    path = Path(path)
    source = str(path)
    try:
        size = path.stat().st_size
        if not path.is_file():
            raise YamlError(f"{source}: not a file", source=source)
        if size > max_bytes:
            raise YamlError(f"{source}: {size} bytes, more than the {max_bytes} a YAML file may hold", source=source)
        raw = path.read_bytes()
    except FileNotFoundError:
        raise YamlError(f"{source}: file not found", source=source) from None
    except OSError as exc:
        raise YamlError(f"{source}: cannot read: {exc.strerror or exc}", source=source) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise YamlError(f"{source}: not a text file: byte 0x{raw[exc.start]:02x} at offset {exc.start} is not "
                        "UTF-8; expected a YAML file", source=source) from None
    return load_yaml_text(text, source, max_depth=max_depth, max_scalar=max_scalar)
