"""What a diverged learner is, and where its state goes instead of the good checkpoint (torch-free).

A gradient step whose TD loss or gradient norm is not finite would turn every weight into NaN;
:class:`der_ros.agent.dqn.DQNAgent` raises :class:`LearnerDiverged` instead of taking it, so the
weights stay the last finite ones. Whoever drives the learner then decides: ``der train`` reports
it in one line, the agent node stops, keeps ``checkpoint_out`` as it was (the last good
checkpoint) and writes the state at divergence beside it (:func:`diverged_path`), for diagnosis.
Kept apart from ``dqn.py`` so the node can name both without importing torch at module load.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["LearnerDiverged", "diverged_path"]


class LearnerDiverged(FloatingPointError):
    """A gradient step would have made the weights non-finite (TD loss or gradient norm inf/NaN).

    Raised *before* the optimizer step, so the agent keeps the last finite weights.
    ``user_facing``: the ``der`` CLI prints the message instead of a traceback.
    """

    user_facing = True


def diverged_path(path: str | os.PathLike[str]) -> Path:
    """Where the state of a diverged learner goes instead of ``path``: ``agent.pt`` -> ``agent.diverged.pt``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.diverged{path.suffix}")
