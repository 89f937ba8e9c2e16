"""The architecture holds: one home for the graph contract, dependencies pointing down, no cycles.

These tests read the package's source (``ast``) or import it in a subprocess; they would fail on
the layout before issue 13 (topic names spelled in six files, a core importing a node, a base
module importing its subclasses, ``nodes`` and ``graph`` importing each other).
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

from der_ros import contract

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("der_ros", "sumo_bridge")
CONTRACT = REPO / "der_ros" / "contract"
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
    files = [f for f in package_files() if CONTRACT not in f.parents]
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


# -- layers and cycles -------------------------------------------------------------------------------
#: module prefix -> layer. An import may go to a lower layer or stay inside its own group (the
#: longest matching prefix); never up, never sideways into another group of the same layer.
LAYERS: dict[str, int] = {
    "der_ros.yaml_loader": -1,  # the one YAML loader: below everything that reads a file
    "der_ros": 0,  # the package itself (__version__)
    "der_ros.configuration": 0,
    "der_ros.contract": 0,
    "der_ros.replay": 1,
    "der_ros.bag": 1,  # MCAP files alone
    "sumo_bridge": 1,
    "der_ros.agent": 2,
    "der_ros.safety": 2,
    "der_ros.train": 3,
    "der_ros.offline": 4,  # tools on recorded bags: stand on bag, contract and train
    "der_ros.experiments": 4,
    "der_ros.contract_ros": 5,  # the ROS edge: rclpy from here up
    "der_ros.offline.play": 6,
    "der_ros.nodes": 6,
    "der_ros.graph": 7,
}
#: entry points (``der`` and its subcommands): may import any layer, imported by nobody
ENTRY_POINTS = {"der_ros.cli", "der_ros.bench_cli", "der_ros.offline.bag_cli", "der_ros.graph.graph_cli",
                "der_ros.train.train_cli", "sumo_bridge.network_cli"}
ENTRY_LAYER = 8
#: below this layer nothing may import ROS (the ROS-free cores)
ROS_LAYER = 5
ROS_PACKAGES = {"rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs", "nav_msgs", "diagnostic_msgs",
                "visualization_msgs",
                "rosgraph_msgs", "builtin_interfaces", "std_srvs", "launch", "launch_ros", "rosidl_runtime_py"}
#: a function may import these lazily (startup time), and project modules that load one of them at the top
HEAVY = {"torch", "matplotlib", *ROS_PACKAGES}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(f): f for f in package_files()}


def group(module: str) -> str:
    """The longest prefix of LAYERS (or the entry point itself) a module belongs to."""
    if module in ENTRY_POINTS:
        return module
    best = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len)
    return best


def layer(module: str) -> int:
    return ENTRY_LAYER if module in ENTRY_POINTS else LAYERS[group(module)]


def imports_of(path: Path, modules: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """(imported name, line, at module top level) for every import statement of a file; project
    imports are resolved to the module they load (``from pkg import mod`` -> ``pkg.mod``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, top) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.module and not child.level:
                for a in child.names:
                    full = f"{child.module}.{a.name}"
                    out.append((full if full in modules else child.module, child.lineno, top))
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, False)
            else:
                visit(child, top)

    visit(tree, True)
    return out


def project_graph() -> dict[str, set[str]]:
    """module -> project modules it imports (top level and inside functions)."""
    modules = all_modules()
    return {m: {n for n, _, _ in imports_of(p, modules) if n in modules and n != m} for m, p in modules.items()}


def test_dependencies_point_down() -> None:
    modules = all_modules()
    wrong = []
    for m, path in modules.items():
        for name, line, _top in imports_of(path, modules):
            root = name.split(".")[0]
            if name in modules:
                if name in ENTRY_POINTS and m != "der_ros.cli":
                    wrong.append(f"{m}:{line} imports the entry point {name}")
                elif group(name) != group(m) and layer(name) >= layer(m):
                    wrong.append(f"{m} (layer {layer(m)}):{line} imports {name} (layer {layer(name)})")
            elif root in ROS_PACKAGES and layer(m) < ROS_LAYER:
                wrong.append(f"{m}:{line} is a ROS-free core but imports {name}")
    assert not wrong, "\n".join(wrong)


def test_no_import_cycle() -> None:
    graph = project_graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def strongconnect(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            strongconnect(v)
    assert len(graph) > 50
    assert not cycles, f"import cycles: {cycles}"


def test_lazy_imports_only_for_heavy_modules() -> None:
    """An import inside a function hides a dependency; allowed only for torch, rclpy, matplotlib
    (and ROS packages), or a project module that loads one of them when imported."""
    modules = all_modules()
    top = {m: {n for n, _, t in imports_of(p, modules) if t} for m, p in modules.items()}
    heavy: dict[str, bool] = {}

    def is_heavy(m: str, seen: frozenset[str] = frozenset()) -> bool:
        if m not in heavy:
            heavy[m] = any(n.split(".")[0] in HEAVY or (n in modules and n not in seen and is_heavy(n, seen | {m}))
                           for n in top[m])
        return heavy[m]

    wrong = [f"{m}:{line} imports {name} inside a function"
             for m, path in modules.items() for name, line, at_top in imports_of(path, modules)
             if not at_top and name in modules and not is_heavy(name)]
    assert not wrong, "move these to the top of the module:\n" + "\n".join(wrong)


def test_cores_import_without_rclpy() -> None:
    """Every ROS-free module (and the ROS-free entry points) imports with rclpy and the ROS message
    packages made unimportable, and none of them loads rclpy behind the scenes."""
    cores = sorted(m for m in all_modules() if layer(m) < ROS_LAYER or m in
                   {"der_ros.cli", "der_ros.offline.bag_cli", "der_ros.train.train_cli", "sumo_bridge.network_cli"})
    assert {"der_ros.contract", "der_ros.replay.double_replay", "der_ros.agent.online", "der_ros.bag.reader",
            "sumo_bridge.lane_change_env", "der_ros.train.runner", "der_ros.experiments.suite"} <= set(cores)
    code = textwrap.dedent(f"""
        import importlib, importlib.abc, sys
        BLOCKED = {sorted(ROS_PACKAGES)!r}
        class NoRos(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError(f"{{name}} is blocked: ROS-free cores must not import it")
                return None
        sys.meta_path.insert(0, NoRos())
        for m in {cores!r}:
            importlib.import_module(m)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not loaded, loaded
        print("imported", len({cores!r}))
    """)
    env = dict(os.environ, DER_ROS_NO_NUMBA="1")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"imported {len(cores)}" in proc.stdout
    # and the check bites: a node module does import rclpy
    code_node = code.replace(repr(cores), repr(["der_ros.nodes.agent_node"]))
    proc = subprocess.run([sys.executable, "-c", code_node], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode != 0 and "is blocked" in proc.stderr


def test_the_product_does_not_import_research() -> None:
    """research/ lives beside the product: no module of der_ros or sumo_bridge imports from it (and the
    checker sees a research import when there is one)."""
    modules = all_modules()
    wrong = [f"{m}:{line} imports {name}" for m, path in modules.items()
             for name, line, _top in imports_of(path, modules) if name.split(".")[0] == "research"]  # fmt: skip
    assert not wrong, "\n".join(wrong)
    sample = REPO / "der_ros" / "_research_check_sample.py"
    sample.write_text("def f():\n    from research.tuning import compare_arms\n    return compare_arms\n")
    try:
        assert [n for n, _, _ in imports_of(sample, modules)] == ["research.tuning"]
    finally:
        sample.unlink()
