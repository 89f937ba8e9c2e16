"""``der table3 --shield-networks``: which networks get the shielded rows; wrong values stop before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from der_ros import cli


def test_a_shield_network_outside_networks_is_refused(tmp_path: Path) -> None:
    argv = ["table3", "--networks", "ring", "--shield", "rss", "--shield-networks", "urban", "--out", str(tmp_path)]
    with pytest.raises(SystemExit, match="--shield-networks 'urban' is not one of --networks \\(ring\\)"):
        cli.main(argv)
    assert not any(tmp_path.iterdir())  # nothing planned, nothing written


def test_shield_networks_without_a_shield_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="--shield-networks need --shield rss"):
        cli.main(["table3", "--networks", "ring", "--shield-networks", "ring", "--out", str(tmp_path)])
