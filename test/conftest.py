"""Shared pytest set-up: keep torch to one thread per test process (2-core machines); Ray's
authentication token of this session in the environment (Ray reads it when imported, so it is set
here, before any test module imports ray; otherwise Ray would write ~/.ray/auth_token)."""

import os
import secrets

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("RAY_AUTH_MODE", "token")
os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # torch is a hard dependency; tests that need it fail on their own
    pass
