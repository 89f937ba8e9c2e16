"""The architecture holds: one home for the graph contract, dependencies pointing down, no cycles.

These tests read the package's source (``ast``) or import it in a subprocess; they would fail on
the layout before issue 13 (topic names spelled in six files, a core importing a node, a base
module importing its subclasses, ``nodes`` and ``graph`` importing each other).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from der_ros import contract

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("der_ros", "sumo_bridge")
CONTRACT = REPO / "der_ros" / "contract.py"
CONTRACT_ROS = REPO / "der_ros" / "contract_ros.py"

TOPIC_NAMES = {spec.name for spec in contract.TOPICS}
STATUS_NAMES = {contract.EPISODE_STATUS, contract.METRICS_STATUS, contract.BRIDGE_STATUS}
#: contract strings that mean nothing else: spelled anywhere outside the contract, they are a copy
UNAMBIGUOUS = {name for name in TOPIC_NAMES | STATUS_NAMES if "/" in name or "_" in name} | {
    "best_effort", "transient_local", "keep_last", "keep_all", "system_default", "best_available",
}
#: calls whose topic argument must come from the contract, never a string literal
TOPIC_CALLS = {
    "create_publisher": 1, "create_subscription": 1, "count_subscribers": 0, "count_publishers": 0,
    "get_publishers_info_by_topic": 0, "get_subscriptions_info_by_topic": 0, "add_topic": 0, "has_topic": 0,
}
#: rclpy's QoS vocabulary: only the one conversion module may spell it
RCLPY_QOS = {"QoSProfile", "ReliabilityPolicy", "DurabilityPolicy", "HistoryPolicy", "qos_profile_sensor_data"}


def package_files() -> Iterator[Path]:
    for pkg in PACKAGES:
        yield from sorted((REPO / pkg).rglob("*.py"))


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def _const(node: ast.AST | None) -> str | None:
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


def _is_roles(node: ast.AST) -> bool:
    """A role -> topic mapping (``roles``, ``scan.roles``): its keys are contract topic names."""
    name = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""
    return "role" in name


def contract_violations(path: Path) -> list[str]:
    """Places in ``path`` that spell a piece of the graph contract instead of importing it."""
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = _docstrings(tree)
    rel = path.relative_to(REPO)
    found = []
    for node in ast.walk(tree):
        line = getattr(node, "lineno", 0)
        text = _const(node)
        if text is not None and id(node) not in docs:
            if text in UNAMBIGUOUS or contract.APPLIED_ACTION_PREFIX in text:
                found.append(f"{rel}:{line}: literal {text!r}")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            pos = TOPIC_CALLS.get(node.func.attr)
            arg = node.args[pos] if pos is not None and len(node.args) > pos else None
            if _const(arg) in TOPIC_NAMES or _const(arg) is not None and _const(arg).lstrip("/") in TOPIC_NAMES:
                found.append(f"{rel}:{line}: {node.func.attr}({_const(arg)!r})")
            for kw in node.keywords:
                if kw.arg in ("name", "topic") and (_const(kw.value) or "").lstrip("/") in TOPIC_NAMES | STATUS_NAMES:
                    found.append(f"{rel}:{line}: {kw.arg}={_const(kw.value)!r}")
            if node.func.attr == "get" and _is_roles(node.func.value) and _const(node.args[0]) in TOPIC_NAMES:
                found.append(f"{rel}:{line}: roles.get({_const(node.args[0])!r})")
        if isinstance(node, ast.Subscript) and _is_roles(node.value) and _const(node.slice) in TOPIC_NAMES:
            found.append(f"{rel}:{line}: roles[{_const(node.slice)!r}]")
        if isinstance(node, ast.Compare):  # status.name == "episode", event == "start"...
            sides = [node.left, *node.comparators]
            names = [s for s in sides if isinstance(s, ast.Attribute) and s.attr in ("name", "topic")]
            consts = [_const(s) for s in sides if _const(s) is not None]
            if names and any(c.lstrip("/") in TOPIC_NAMES | STATUS_NAMES for c in consts):
                found.append(f"{rel}:{line}: comparison with {consts}")
        if path != CONTRACT_ROS:
            ident = node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None
            if ident in RCLPY_QOS:
                found.append(f"{rel}:{line}: rclpy QoS {ident}")
            if isinstance(node, ast.ImportFrom):
                found += [f"{rel}:{line}: imports {a.name}" for a in node.names if a.name in RCLPY_QOS]
    return found


def test_no_module_but_the_contract_spells_topics_qos_or_status_names() -> None:
    files = [f for f in package_files() if f != CONTRACT]
    assert len(files) > 50
    violations = [v for f in files for v in contract_violations(f)]
    assert not violations, "spell these through der_ros.contract:\n" + "\n".join(violations)


def test_the_contract_check_catches_copies(tmp_path: Path) -> None:
    """The checker itself finds the kinds of copies it is meant to forbid."""
    sample = REPO / "der_ros" / "_contract_check_sample.py"
    sample.write_text(
        'def f(node, status, roles, cls, cb, q):\n'
        '    node.create_subscription(cls, "state", cb, q)\n'
        '    if status.name == "episode":\n'
        '        return roles.get("reward")\n'
        '    return "applied_action=" + "best_effort"\n'
    )
    try:
        found = contract_violations(sample)
    finally:
        sample.unlink()
    assert len(found) == 5, found
