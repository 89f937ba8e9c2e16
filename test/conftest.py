"""Shared pytest set-up.

- The helper modules (``ros_harness``, ``ray_helpers``, ``bag_helpers``, ``ros_messages``) live at
  ``test/``; the tests live in folders by layer (``test/replay``, ``test/nodes``...): ``test/`` and
  its folders go on ``sys.path``.
- Tiers (markers registered in ``pyproject.toml``, ``--strict-markers``): every test that uses the
  ROS harness's fixtures (``ros_graph``, ``ros_domain``: real node processes on their own
  ``ROS_DOMAIN_ID``) is marked ``ros`` here, automatically; tests that start ROS another way carry
  the mark themselves. Ray and multi-seed suite smoke runs are marked ``slow``. The fast tier is
  ``./scripts/test.sh -m "not ros and not slow"``.
- Torch keeps to one thread per test process (2-core machines); Ray's authentication token of this
  session is in the environment (Ray reads it when imported, so it is set here, before any test
  module imports ray; otherwise Ray would write ~/.ray/auth_token).
"""

import os
import secrets
import sys
from pathlib import Path

import pytest

TEST_ROOT = Path(__file__).resolve().parent
# the helpers, and the layer folders: a few tests reuse another test module's helpers
# (``from test_scene import check_against_libsumo``), also when that folder is not being collected
_LAYERS = sorted(p for p in TEST_ROOT.iterdir() if p.is_dir() and p.name.isidentifier() and not p.name.startswith("_"))
for _folder in [TEST_ROOT, *_LAYERS]:
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_AUTH_MODE", "token")
os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # torch is a hard dependency; tests that need it fail on their own
    pass

#: fixtures of test/ros_harness.py that start ROS node processes or give the test a ROS domain
ROS_FIXTURES = frozenset({"ros_graph", "ros_domain"})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark ``ros`` every test that uses a ROS fixture, directly or through another fixture."""
    for item in items:
        if ROS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.ros)
