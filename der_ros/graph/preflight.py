"""What ``der graph`` checks about files and paths before any process starts.

:func:`der_ros.nodes.params.build_graph_params` checks every parameter *value* as the nodes will;
this module checks what a value points at, which only the file system can tell -- so that a run
that cannot succeed is refused in one line (exit 2) instead of failing after the recorder and the
agent were started (issue 45):

* ``agent_node/checkpoint_in``: the file exists, is a der_ros checkpoint (loaded exactly as the
  agent node loads it), fits the graph's observation and actions, and holds finite weights;
* every output -- ``recorder_node/output`` (a bag directory that must not exist or be empty),
  ``agent_node/checkpoint_out`` and ``policy_dir`` -- can be created: its nearest existing
  parent is a writable directory, and it is not something else already;
* ``agent_node/step_seconds`` equals the bridge's step (``scenario.step_length`` x
  ``scenario.decision_interval``): 0 turns off the agent's window and its lost-step detection,
  any other value makes every step look like a gap.

Errors use the one-line layout of :mod:`der_ros.nodes.param_check`:
``<origin>/<node>/<name> = <value>: <reason>``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from der_ros.configuration import ConfigError, from_dict, unflatten_names
from der_ros.nodes.param_check import parameter_error
from sumo_bridge.observation import ObservationConfig, empty_points, encode_observation

__all__ = ["check_graph_files", "writable_problem"]

#: (node, parameter) -> where its value came from (the params file, ``-p``, ``--run-dir``...)
OriginOf = Callable[[str, str], str]


def writable_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` cannot be written as an output of ``kind`` (None if it can): ``"new_dir"`` may
    exist only as an empty directory (a bag), ``"dir"`` only as a writable directory, ``"file"``
    only as a writable file."""
    if path.exists() or path.is_symlink():
        if kind in ("new_dir", "dir"):
            if not path.is_dir():
                return "exists and is not a directory"
            if kind == "new_dir" and any(path.iterdir()):
                return "exists and is not empty (not overwriting)"
            return None if os.access(path, os.W_OK | os.X_OK) else "is not writable"
        if path.is_dir():
            return "is a directory, expected a file path"
        return None if os.access(path, os.W_OK) and os.access(path.parent, os.W_OK | os.X_OK) else "is not writable"
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot be created: {parent} is not a directory"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot be created: {parent} is not writable"
    return None


def _check_checkpoint(value: str, agent: Mapping[str, Any], origin: str) -> None:
    from der_ros.agent.dqn import DQNAgent  # lazy: torch

    def fail(reason: str) -> ConfigError:
        return parameter_error(origin, "agent_node", "checkpoint_in", value, reason)

    path = Path(value)
    if not path.is_file():
        raise fail("no such file" if not path.exists() else "not a file")
    try:
        loaded = DQNAgent.load(path)
    except Exception as exc:  # noqa: BLE001 - any unpickling / layout error: not one of our checkpoints
        detail = " ".join(str(exc).split())[:60]
        raise fail(f"not a der_ros checkpoint ({type(exc).__name__}: {detail})") from None
    obs_cfg = from_dict(ObservationConfig, unflatten_names(dict(agent), "observation"), source="agent_node")
    obs_shape = tuple(encode_observation(empty_points(), obs_cfg).shape)
    n_actions = int(agent.get("n_actions", 3))
    if tuple(loaded.obs_shape) != obs_shape or int(loaded.n_actions) != n_actions:
        raise fail(f"a checkpoint for observations {tuple(loaded.obs_shape)} and {loaded.n_actions} actions, expected "
                   f"{obs_shape} and {n_actions}")
    if not loaded.parameters_finite():
        raise fail("its weights are not finite (a diverged learner); load an earlier checkpoint")


def check_graph_files(params: Mapping[str, Any], origin_of: OriginOf) -> None:
    """Raise :class:`ConfigError` (one line) if a path of the graph's ``params`` cannot work."""
    agent = params["agent_node"]["ros__parameters"]
    bridge = params["bridge_node"]["ros__parameters"]
    recorder = params["recorder_node"]["ros__parameters"]

    step = float(bridge.get("scenario.step_length", 0.1)) * int(bridge.get("scenario.decision_interval", 5))
    seconds = float(agent.get("step_seconds", 0.0))
    if not math.isclose(seconds, step, rel_tol=1e-9, abs_tol=1e-12):
        raise parameter_error(origin_of("agent_node", "step_seconds"), "agent_node", "step_seconds", seconds,
                              f"expected the bridge's step, {step:g} s (scenario.step_length x "
                              "scenario.decision_interval)")
    outputs = [("recorder_node", "output", recorder.get("output", ""), "new_dir"),
               ("agent_node", "checkpoint_out", agent.get("checkpoint_out", ""), "file"),
               ("agent_node", "policy_dir", agent.get("policy_dir", ""), "dir")]
    for node, name, value, kind in outputs:
        if not value:
            continue
        problem = writable_problem(Path(value), kind)
        if problem is not None:
            raise parameter_error(origin_of(node, name), node, name, value, problem)
    if agent.get("checkpoint_in"):
        _check_checkpoint(str(agent["checkpoint_in"]), agent, origin_of("agent_node", "checkpoint_in"))
