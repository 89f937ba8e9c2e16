"""Shared pytest set-up: keep torch to one thread per test process (2-core machines)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # torch is a hard dependency; tests that need it fail on their own
    pass
