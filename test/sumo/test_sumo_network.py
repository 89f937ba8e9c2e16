"""Network builds: lane layout and lengths, the source-hash cache, clear build errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import sumolib

from sumo_bridge import network_build
from sumo_bridge.network_build import NetworkBuildError, build_network


def _net(name: str) -> sumolib.net.Net:
    return sumolib.net.readNet(str(build_network(name).net_file), withInternal=True)


def test_ring_has_two_lanes_and_a_377m_lap() -> None:
    net = _net("ring")
    normal = [e for e in net.getEdges() if e.getFunction() != "internal"]
    assert sorted(e.getID() for e in normal) == ["bottom", "left", "right", "top"]
    assert all(e.getLaneNumber() == 2 for e in normal)
    # lap along lane 0 including the junctions' internal lanes
    lap = sum(e.getLanes()[0].getLength() for e in net.getEdges())
    assert 370.0 < lap < 385.0
    # counter-clockwise driving: lane 0 (rightmost) is the outer lane
    centre = (60.0, 60.0)  # netconvert moves the ring's centre from (0, 0) to (60, 60)
    bottom = net.getEdge("bottom")
    r0 = [((x - centre[0]) ** 2 + (y - centre[1]) ** 2) ** 0.5 for x, y in bottom.getLanes()[0].getShape()]
    r1 = [((x - centre[0]) ** 2 + (y - centre[1]) ** 2) ** 0.5 for x, y in bottom.getLanes()[1].getShape()]
    assert min(r0) > max(r1)


def test_urban_bridge_has_three_lanes_each_way() -> None:
    net = _net("urban")
    for eid in ("100", "-100"):
        edge = net.getEdge(eid)
        assert edge.getLaneNumber() == 3
        assert 900.0 < edge.getLength() < 1100.0
    route_file = build_network("urban").route_file.read_text()
    assert 'id="ego_route"' in route_file and "<flow " in route_file


def _copy_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    pkg = tmp_path / "pkg"
    shutil.copytree(network_build.PACKAGE_DIR / "networks" / "ring", pkg / "networks" / "ring")
    monkeypatch.setattr(network_build, "PACKAGE_DIR", pkg)
    return pkg / "networks" / "ring"


def test_cache_is_reused_and_rebuilt_when_a_source_changes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = _copy_sources(tmp_path, monkeypatch)
    cache = tmp_path / "cache"
    first = build_network("ring", cache_dir=cache)
    mtime = first.net_file.stat().st_mtime_ns
    again = build_network("ring", cache_dir=cache)
    assert again.stamp == first.stamp and again.net_file.stat().st_mtime_ns == mtime  # cached
    edg = src / "ring.edg.xml"
    edg.write_text(edg.read_text().replace('speed="13.89"', 'speed="20.00"'))
    rebuilt = build_network("ring", cache_dir=cache)
    assert rebuilt.stamp != first.stamp
    assert 'speed="20.00"' in rebuilt.net_file.read_text()


def test_build_failure_reports_netconvert_stderr(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = _copy_sources(tmp_path, monkeypatch)
    edg = src / "ring.edg.xml"
    edg.write_text(edg.read_text().replace('from="bottom"', 'from="nowhere"'))
    with pytest.raises(NetworkBuildError, match="nowhere") as exc:
        build_network("ring", cache_dir=tmp_path / "cache")
    assert "netconvert failed" in str(exc.value) and "stderr" in str(exc.value)


def test_missing_sumo_binary_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sumolib, "checkBinary", lambda name: f"/nonexistent/{name}")
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(network_build.SumoNotFoundError, match="'sumo-gui' not found.*eclipse-sumo"):
        network_build.sumo_binary("sumo-gui")


def test_cache_falls_back_to_user_dir_when_package_is_read_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package_build = network_build.PACKAGE_DIR / "networks" / "build"
    real_writable = network_build._writable
    # a read-only install: the package's build folder cannot be written (chmod does not stop root)
    monkeypatch.setattr(network_build, "_writable", lambda path: path != package_build and real_writable(path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("DER_ROS_NETWORK_CACHE", raising=False)
    root = network_build.cache_root()
    assert root == tmp_path / "xdg" / "der_ros" / "networks"
    built = build_network("ring", cache_dir=root)
    assert built.net_file.is_file() and built.net_file.is_relative_to(tmp_path)
