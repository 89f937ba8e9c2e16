"""The one YAML loader (issue 45, finding 2): generated documents either load exactly or are refused
with one short line naming file, key and line."""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from der_ros.configuration import ConfigError, read_yaml_mapping
from der_ros.yaml_loader import MAX_BYTES, MAX_DEPTH, MAX_SCALAR, YamlError, load_yaml, load_yaml_text

# -- scalars: (spelling, what YAML 1.2 means by it) or (spelling, REFUSED) -------------------------------
REFUSED = object()
NUMBERS = [
    ("1e-3", 0.001), ("1E5", 100000.0), ("-2.5e+2", -250.0), (".5", 0.5), ("5.", 5.0), ("+7", 7), ("-0", 0),
    ("0o17", 15), ("0x1F", 31), ("12", 12), ("0.0005", 0.0005), (".inf", math.inf), ("-.Inf", -math.inf),
    ("true", True), ("False", False), ("~", None), ("null", None),
]
AMBIGUOUS = ["yes", "No", "on", "OFF", "y", "017", "00", "09", "1_000", "1:30", "0b101", "1.0_0"]
KEYS = ["a", "b", "lr", "agent"]


@dataclass
class Doc:
    lines: list[str] = field(default_factory=list)
    #: problems the loader must refuse: (kind, key path, line, first line of a duplicate)
    problems: list[tuple[str, str, int, int | None]] = field(default_factory=list)


def key_path(parts: list[str]) -> str:
    if len(parts) > 6:
        parts = [*parts[:3], "...", *parts[-2:]]
    out = ""
    for part in parts:  # a.b[0].c, shortened to a.b.c...y.z
        out += part if part.startswith("[") or part == "..." or not out or out.endswith("...") else "." + part
    return out


scalars = st.one_of(
    st.sampled_from(NUMBERS),
    st.sampled_from(AMBIGUOUS).map(lambda s: (s, REFUSED)),
    st.integers(-(2**40), 2**40).map(lambda i: (str(i), i)),
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(lambda f: (repr(f), f)),
    st.text(st.sampled_from("abcxyz019 -_.:/"), max_size=12).map(lambda s: (f'"{s}"', s)),
    st.from_regex(r"\Ak[a-z_]{0,8}\Z").map(lambda s: (s, s)),
    st.just(("<huge>", "HUGE")),  # rendered as MAX_SCALAR + 1 characters
)


def pairs(children: st.SearchStrategy) -> st.SearchStrategy:
    return st.lists(st.tuples(st.sampled_from(KEYS), children), max_size=4)  # keys repeat: duplicates


tree = st.recursive(
    scalars,
    lambda children: st.one_of(
        pairs(children).map(lambda p: ("map", p)),
        st.lists(children, max_size=3).map(lambda x: ("seq", x)),
    ),
    max_leaves=12,
)
deep = st.tuples(st.sampled_from(KEYS), st.integers(1, 3 * MAX_DEPTH), scalars).map(lambda t: ("deep", t))
documents = pairs(st.one_of(tree, deep))


def render(node: Any, doc: Doc, indent: int, path: list[str], depth: int, prefix: str) -> Any:
    """Append the YAML lines of ``node`` (the first one after ``prefix``); returns the expected value."""
    pad = " " * indent
    if isinstance(node, tuple) and node and node[0] == "deep":
        key, levels, leaf = node[1]
        return render(("map", [(key, ("deepmap", levels - 1, leaf))]), doc, indent, path, depth, prefix)
    if isinstance(node, tuple) and node and node[0] == "deepmap":
        _, levels, leaf = node
        inner = leaf if levels == 0 else ("deepmap", levels - 1, leaf)
        return render(("map", [("k", inner)]), doc, indent, path, depth, prefix)
    if isinstance(node, tuple) and node and node[0] in ("map", "seq"):
        kind, items = node
        if depth + 1 > MAX_DEPTH:  # refused where the collection starts: its first item, or its {} / []
            doc.problems.append(("deep", key_path(path), len(doc.lines) + 1 + bool(prefix and items), None))
        if not items:
            empty = "{}" if kind == "map" else "[]"
            doc.lines.append(f"{prefix} {empty}" if prefix else empty)
            return {} if kind == "map" else []
        if prefix:
            doc.lines.append(prefix)
        if kind == "seq":
            out_list = []
            for i, item in enumerate(items):
                out_list.append(render(item, doc, indent + 2, [*path, f"[{i}]"], depth + 1, pad + "-"))
            return out_list
        out: dict[str, Any] = {}
        first: dict[str, int] = {}
        for key, value in items:
            line = len(doc.lines) + 1
            if key in first:
                doc.problems.append(("duplicate", key_path([*path, key]), line, first[key]))
            first.setdefault(key, line)
            out[key] = render(value, doc, indent + 2, [*path, key], depth + 1, f"{pad}{key}:")
        return out
    text, expected = node
    if expected == "HUGE":
        text = "x" * (MAX_SCALAR + 1)
    line = len(doc.lines) + 1
    doc.lines.append(f"{prefix} {text}" if prefix else text)
    if expected is REFUSED:
        doc.problems.append(("ambiguous", key_path(path), line, None))
    elif expected == "HUGE":
        doc.problems.append(("huge", key_path(path), line, None))
    return expected


def check_one_short_line(message: str, source: str) -> None:
    assert "\n" not in message and len(message) <= 200, message
    assert message.startswith(source), message


def load_document(items) -> tuple[Doc, Any, Any]:
    doc = Doc()
    expected = render(("map", items), doc, 0, [], 0, "")
    text = "\n".join(doc.lines) + "\n"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.yaml"
        path.write_text(text)
        try:
            return doc, expected, load_yaml(path)
        except YamlError as exc:
            check_one_short_line(str(exc), str(path))
            return doc, expected, exc


def check_document(items) -> None:
    doc, expected, got = load_document(items)
    if not doc.problems:
        assert not isinstance(got, YamlError), f"refused a good document: {got}"
        assert got == expected or (got is None and expected == {})
        return
    assert isinstance(got, YamlError), f"loaded a document with {doc.problems[0]}"
    found = []
    for kind, key, line, first in doc.problems:
        what = {"duplicate": f"duplicate key (first at line {first})", "deep": "nested deeper than",
                "ambiguous": "means something else in YAML 1.1", "huge": "characters"}[kind]
        if got.line == line and what in str(got) and (kind == "deep" or got.key == key):
            found.append(kind)
    assert found, f"refusal {str(got)!r} (key {got.key!r}, line {got.line}) is none of {doc.problems}"


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(documents)
def test_generated_documents_load_exactly_or_are_refused_in_one_line(items):
    check_document(items)


@pytest.mark.slow
@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(documents)
def test_generated_documents_many_examples(items):
    check_document(items)


# -- the probes of the issue -------------------------------------------------------------------------------
def test_a_second_section_is_refused_naming_both_lines(tmp_path):
    path = tmp_path / "train.yaml"
    path.write_text("agent:\n  lr: 0.0005\n  gamma: 0.98\nenv:\n  name: ring\nagent:\n  lr: 100\n")
    with pytest.raises(ConfigError) as exc:
        read_yaml_mapping(path)
    assert str(exc.value) == f"{path}: line 6: key 'agent': duplicate key (first at line 1)"


def test_deep_nesting_is_refused_not_a_recursion_error(tmp_path):
    path = tmp_path / "deep.yaml"
    path.write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(YamlError, match=rf"^{path}: line 1: key 'a\[0\]\[0\]\.\.\.\[0\]\[0\]': nested deeper"):
        load_yaml(path)
    path.write_text("".join(" " * i + "k:\n" for i in range(1000)) + " " * 1000 + "k: 1\n")
    with pytest.raises(YamlError, match="nested deeper than 64 levels"):
        load_yaml(path)


def test_a_huge_value_is_quoted_as_a_short_excerpt(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text("agent:\n  lr: " + "9" * (MAX_BYTES + 10) + "\n")
    with pytest.raises(YamlError) as exc:
        load_yaml(path)
    assert len(str(exc.value)) < 150 and "more than the" in str(exc.value)
    path.write_text("agent:\n  lr: " + "9" * 5000 + "\n")  # within the scalar limit; int() refuses it
    with pytest.raises(YamlError, match=rf"^{path}: line 2: key 'agent.lr': an integer of 5000 digits"):
        load_yaml(path)
    path.write_text("agent:\n  lr: 1e999\n")  # would be read as inf
    with pytest.raises(YamlError, match=rf"^{path}: line 2: key 'agent.lr': '1e999' is beyond the float range"):
        load_yaml(path)


def test_yaml_1_2_numbers_and_the_config_layer(tmp_path):
    assert load_yaml_text("lr: 1e-3\nb: 5E-4\nc: 0o10") == {"lr": 0.001, "b": 0.0005, "c": 8}
    from der_ros.train.config import load_experiment_config

    path = tmp_path / "t.yaml"
    path.write_text("agent:\n  lr: 1e-3\n")
    assert load_experiment_config(path).agent.lr == 0.001
    path.write_text("agent:\n  lr: 1e30\n")
    with pytest.raises(ConfigError, match=r"lr = 1e\+30, .*<= 1"):
        load_experiment_config(path)


def test_a_huge_value_in_a_config_error_is_cut(tmp_path):
    path = tmp_path / "t.yaml"
    path.write_text("agent:\n  lr: \"" + "z" * 50_000 + "\"\n")
    from der_ros.train.config import load_experiment_config

    with pytest.raises(ConfigError) as exc:
        load_experiment_config(path)
    assert len(str(exc.value)) < 250 and "(50000 characters)" in str(exc.value)


def test_der_train_refuses_a_repeated_section_before_training(tmp_path, capsys):
    """Issue 45: a second ``agent:`` section replaced the first and der train trained on it with rc 0."""
    from der_ros import cli

    path = tmp_path / "lying.yaml"
    path.write_text((Path(__file__).resolve().parents[1] / "config" / "cartpole.yaml").read_text()
                    + "\nagent:\n  lr: 0.5\n")
    first = next(i for i, x in enumerate(path.read_text().splitlines(), 1) if x.startswith("agent:"))
    last = len(path.read_text().splitlines()) - 1
    assert cli.main(["train", "--config", str(path), "--run-dir", str(tmp_path / "run")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"der train: configuration error: {path}: line {last}: key 'agent': duplicate key (first at line {first})")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("text", "check"), [(".nan", math.isnan), (".NaN", math.isnan), ("-.inf", lambda v: v == -math.inf),
                                             (".inf", lambda v: v == math.inf)])  # fmt: skip
def test_yaml_special_floats_load_as_floats(text: str, check) -> None:
    """``.nan`` / ``.inf`` are YAML's float spellings: loaded as floats, so the config check can name them
    (``lam = nan, expected a finite number``) instead of a parser error."""
    value = load_yaml_text(f"x: {text}\n", "t.yaml")["x"]
    assert isinstance(value, float) and check(value)
