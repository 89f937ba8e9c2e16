"""ament_python package that also installs with plain pip (see README)."""

import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).parent
PACKAGE = "der_ros"


def _version() -> str:
    text = (HERE / "package.xml").read_text()
    match = re.search(r"<version>([^<]+)</version>", text)
    if match is None:
        raise RuntimeError("package.xml has no <version>")
    return match.group(1).strip()


def _requirements() -> list[str]:
    lines = (HERE / "requirements.txt").read_text().splitlines()
    return [ln.split("#")[0].strip() for ln in lines if ln.split("#")[0].strip()]


def _tree(src: str, dest_root: str) -> list[tuple[str, list[str]]]:
    """data_files entries for every file under ``src`` (keeping sub-folders)."""
    out: dict[str, list[str]] = {}
    for path in sorted(Path(HERE, src).rglob("*")):
        if path.is_file() and "build" not in path.relative_to(HERE).parts[1:] and "__pycache__" not in path.parts:
            rel = path.relative_to(HERE)
            out.setdefault(str(Path(dest_root) / rel.parent), []).append(str(rel))
    return sorted(out.items())


setup(
    name=PACKAGE,
    version=_version(),
    packages=find_packages(include=["der_ros", "der_ros.*", "sumo_bridge", "sumo_bridge.*"]),
    package_data={"sumo_bridge": ["networks/*/*.xml", "networks/*/*.osm", "networks/*/*.cfg"]},
    include_package_data=True,
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/launch", sorted(glob("launch/*.py"))),
        ("share/" + PACKAGE + "/config", sorted(glob("config/*.yaml"))),
        *_tree("sumo_bridge/networks", "share/" + PACKAGE),
    ],
    install_requires=_requirements(),
    zip_safe=False,
    maintainer="der_ros developers",
    maintainer_email="der-ros@users.noreply.github.com",
    description="DQN with Double Experience Replay for SUMO lane changing, with ROS 2 nodes",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "der = der_ros.cli:main",
            "bridge_node = der_ros.nodes.bridge_node:main",
            "agent_node = der_ros.nodes.agent_node:main",
            "recorder_node = der_ros.nodes.recorder_node:main",
            "safety_node = der_ros.nodes.safety_node:main",
        ],
    },
)
