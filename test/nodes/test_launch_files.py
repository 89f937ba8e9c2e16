"""Launch files are checked without the ``launch`` packages (not on PyPI): parsed with ``ast``.

For every ``Node(...)`` action: the package is der_ros, the executable is a console script of
setup.py whose module imports and whose function exists, the node name has a section in the
params file, and every parameter key (params file section and inline dicts) is declared by that
node. Every params file referenced through ``PathJoinSubstitution([FindPackageShare("der_ros"),
...])`` exists, is installed by setup.py, and parses as YAML with ``ros__parameters``; every
``LaunchConfiguration`` used is declared.
"""

from __future__ import annotations

import ast
import importlib
from glob import glob
from pathlib import Path

import pytest
import yaml

from der_ros.nodes.params import flat_specs

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))
STANDARD = {"use_sim_time"}  # declared by rclpy itself


def _call_name(node: ast.Call) -> str:
    f = node.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def _kw(node: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in node.keywords if k.arg == name), None)


def _const(node: ast.expr | None) -> object:
    return node.value if isinstance(node, ast.Constant) else None


def console_scripts() -> dict[str, str]:
    """name -> "module:function" from setup.py's entry_points (parsed, not installed metadata)."""
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values):
                if _const(k) == "console_scripts" and isinstance(v, ast.List):
                    out = {}
                    for elt in v.elts:
                        name, _, target = str(_const(elt)).partition("=")
                        out[name.strip()] = target.strip()
                    return out
    raise AssertionError("setup.py declares no console_scripts")


def installed_data_files() -> set[str]:
    """Repo-relative files setup.py installs into share/der_ros (config/*.yaml, launch/*.py)."""
    text = (REPO / "setup.py").read_text()
    out: set[str] = set()
    for pattern in ("launch/*.py", "config/*.yaml"):
        assert f'glob("{pattern}")' in text, f"setup.py no longer installs {pattern}"
        out |= {str(Path(p)) for p in glob(str(REPO / pattern))}
    return {str(Path(p).relative_to(REPO)) for p in out}


def declared_parameters(module_name: str) -> set[str]:
    module = importlib.import_module(module_name)
    sections = module.parameter_sections()
    return {name for prefix, obj in sections.items() for name in flat_specs(obj, prefix)} | STANDARD


class LaunchInfo:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.tree = ast.parse(path.read_text(), filename=str(path))
        self.calls = [n for n in ast.walk(self.tree) if isinstance(n, ast.Call)]
        self.nodes = [c for c in self.calls if _call_name(c) == "Node"]
        self.declared_args = {_const(c.args[0]) for c in self.calls if _call_name(c) == "DeclareLaunchArgument" and c.args}
        self.used_args = {_const(c.args[0]) for c in self.calls if _call_name(c) == "LaunchConfiguration" and c.args}
        self.params_files: list[str] = []
        for c in self.calls:
            if _call_name(c) == "PathJoinSubstitution" and c.args and isinstance(c.args[0], ast.List):
                elts = c.args[0].elts
                first = elts[0]
                assert isinstance(first, ast.Call) and _call_name(first) == "FindPackageShare"
                assert _const(first.args[0]) == "der_ros", f"{path}: only der_ros share files are checked"
                parts = [_const(e) for e in elts[1:]]
                assert all(isinstance(p, str) for p in parts), f"{path}: non-literal path parts {parts}"
                self.params_files.append("/".join(parts))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def scripts() -> dict[str, str]:
    return console_scripts()


def test_there_are_launch_files_and_they_are_installed() -> None:
    names = {p.name for p in LAUNCH_FILES}
    assert "der_graph.launch.py" in names
    installed = installed_data_files()
    for p in LAUNCH_FILES:
        assert str(p.relative_to(REPO)) in installed


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file(path: Path, scripts: dict[str, str]) -> None:
    info = LaunchInfo(path)
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in info.tree.body)
    assert info.nodes, f"{path.name} starts no Node"
    assert info.used_args <= info.declared_args, f"undeclared launch arguments {info.used_args - info.declared_args}"

    installed = installed_data_files()
    params_docs = {}
    for rel in info.params_files:
        assert (REPO / rel).is_file(), f"{path.name} references {rel}, which does not exist"
        assert rel in installed, f"{rel} is not installed by setup.py"
        doc = yaml.safe_load((REPO / rel).read_text())
        assert isinstance(doc, dict) and all("ros__parameters" in v for v in doc.values()), rel
        params_docs[rel] = doc
    assert params_docs, f"{path.name} references no params file of the package"

    for call in info.nodes:
        package, executable, name = (_const(_kw(call, k)) for k in ("package", "executable", "name"))
        assert package == "der_ros", f"{path.name}: package {package!r}"
        assert executable in scripts, f"{path.name}: executable {executable!r} is not a console script of setup.py"
        module_name, _, func = scripts[executable].partition(":")
        module = importlib.import_module(module_name)
        assert callable(getattr(module, func, None)), f"{scripts[executable]} is not callable"
        node_name = name or executable
        declared = declared_parameters(module_name)
        params = _kw(call, "parameters")
        assert isinstance(params, ast.List), f"{path.name}: {executable} has no parameters list"
        for item in params.elts:
            if isinstance(item, ast.Dict):
                keys = {_const(k) for k in item.keys}
                assert keys <= declared, f"{path.name}: {executable} inline keys not declared: {keys - declared}"
        for rel, doc in params_docs.items():
            assert node_name in doc, f"{rel} has no section for node {node_name!r}"
            keys = set(doc[node_name]["ros__parameters"])
            assert keys <= declared, f"{rel} [{node_name}]: keys the node does not declare: {sorted(keys - declared)}"


def test_checker_catches_an_undeclared_key(tmp_path: Path, scripts: dict[str, str]) -> None:
    """The checks above can fail: an inline key the node does not declare is detected."""
    bad = (REPO / "launch" / "der_graph.launch.py").read_text().replace('"max_steps":', '"max_stepz":')
    tree = ast.parse(bad)
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and _call_name(n) == "Node"]
    bridge = next(c for c in calls if _const(_kw(c, "executable")) == "bridge_node")
    declared = declared_parameters(scripts["bridge_node"].partition(":")[0])
    keys = {_const(k) for item in _kw(bridge, "parameters").elts if isinstance(item, ast.Dict) for k in item.keys}
    assert "max_stepz" in keys - declared
