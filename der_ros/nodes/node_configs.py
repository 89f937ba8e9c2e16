"""The parameters of each node of the graph, as config dataclasses (ROS-free).

A node declares one ROS parameter per field of its sections (:mod:`der_ros.nodes.params`):
its own config (top-level names) and the core configs it builds on (``agent.*``,
``replay.*``, ``scenario.*``...). Kept apart from the rclpy node modules so that ``der graph``
can validate a run's parameters, and tools can write params files, without importing ROS,
torch or SUMO.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from der_ros.agent.config import DQNConfig
from der_ros.bag.recorder_config import RecorderConfig
from der_ros.configuration import param
from der_ros.replay.config import ReplayConfig
from der_ros.safety.config import SafetyConfig
from sumo_bridge.observation import ObservationConfig
from sumo_bridge.scenario import ScenarioConfig

__all__ = ["BridgeNodeConfig", "AgentNodeConfig", "SafetyNodeConfig", "SAFETY_FLAG", "AGENT_MUTABLE", "NODE_SECTIONS", "parameter_sections"]


@dataclass
class BridgeNodeConfig:
    """Parameters of the bridge node itself (top-level ROS parameter names)."""

    mode: str = param("lockstep", "stepping mode: 'lockstep' (wait for each command) or 'free_run' (timer)",
                      choices=("lockstep", "free_run"))
    command_timeout: float = param(
        2.0, "lockstep: seconds to wait for the command answering a state before applying the default action "
        "(0 = keep lane; the next reward's frame_id names the applied action, so the learner stores what was applied); "
        "keep it above the agent's longest pause (checkpoint save)", low=0.0, low_inclusive=False)
    real_time_factor: float = param(
        1.0, "free_run: simulated seconds per wall-clock second", low=0.0, low_inclusive=False)
    max_steps: int = param(0, "simulation steps before the node exits 0 (0 = unlimited)", low=0)
    wait_for_agent: float = param(
        30.0, "seconds to wait at start-up until state/reward have a subscriber and lane_change_cmd a publisher "
        "(0 = start at once)", low=0.0)
    min_subscribers: int = param(
        1, "start-up: subscribers that state and reward must each have before the first step (der graph sets 2: "
        "agent + recorder, so the bag starts with the first state)", low=1)
    diagnostics_every: int = param(200, "publish bridge/diagnostics every this many steps", low=1)
    map_frame: str = param("map", "frame_id of ego/odom and of the scene markers")
    markers: bool = param(
        True, "publish the scene for RViz / Foxglove / der bag render: every vehicle on scene/vehicles each step "
        "and the road once on scene/road (visualization_msgs/MarkerArray); costs SUMO position subscriptions and "
        "the encoding, see bench/graph.py")
    command_queue_depth: int = param(
        1000, "KEEP_LAST depth of the lane_change_cmd subscription; each command callback also takes every command "
        "already queued (up to this many), so a flood of stray commands is judged and rejected before it can push "
        "the agent's answer out of the queue", low=1, high=100_000)


@dataclass
class AgentNodeConfig:
    """Parameters of the agent node itself (top-level ROS parameter names)."""

    seed: int = param(0, "seed of the learner (network init, exploration, replay sampling)", low=0)
    device: str = param("cpu", "torch device: 'cpu', 'cuda', 'cuda:N' or 'auto'")
    n_actions: int = param(3, "number of actions (0 keep lane, 1 left, 2 right)", low=2)
    checkpoint_in: str = param("", "checkpoint to load at start (empty = start from scratch)")
    checkpoint_out: str = param("", "checkpoint file written periodically and on shutdown (empty = never)")
    checkpoint_every: int = param(5000, "save every this many environment steps (0 = only on shutdown / service)",
                                  low=0)
    policy_every: int = param(
        0, "write the Q-network's weights to policy_dir every this many environment steps (and at start), for "
        "der graph's greedy evaluations in another process (0 = never)", low=0)
    policy_dir: str = param("", "folder of the policy snapshots (policy_<steps>.npz, a few tens of kB each)")
    metrics_every: int = param(100, "publish agent/metrics every this many gradient-step calls (and at every "
                               "episode end)", low=1)
    evaluate: bool = param(False, "start paused: evaluation mode (greedy actions, no learning)")
    step_seconds: float = param(
        0.0, "the bridge's step in seconds, to detect steps lost on every topic (0 = do not check)", low=0.0)
    max_buffered: int = param(64, "incomplete state/reward stamps kept while waiting for the other half", low=1)
    max_abs_reward: float = param(
        1e6, "rewards larger than this in magnitude are rejected as malformed: no scenario gives them (SUMO's are "
        "+-100 plus a log speed), and they would overflow the squared TD loss", low=0.0, low_inclusive=False,
        high=3.0e38)
    torch_threads: int = param(1, "torch intra-op threads (1 keeps the node from competing with SUMO)", low=1)
    min_command_subscribers: int = param(
        0, "start-up: the node reports 'agent ready' only once its lane_change_cmd publisher is matched by this many "
        "subscriptions, seen on 4 checks 0.05 s apart (der graph sets 1 when it records the commands: the recorder, "
        "started first, so the bag holds the first command too; 0 = ready at once)", low=0)
    command_wait_timeout: float = param(
        30.0, "seconds to wait for min_command_subscribers before reporting ready anyway (with a warning)", low=0.0)
    warm_up: bool = param(
        True, "before joining the graph, run act/observe/learn on a scratch agent so that lazy set-up (the replay's "
        "numba kernels, torch autograd) does not stall the first real steps past the bridge's command timeout")


@dataclass
class SafetyNodeConfig:
    """Parameters of the safety node itself (top-level names); the shield's own are ``safety.*``."""

    max_state_age: float = param(
        1.0, "seconds (wall clock) a state may be old when the command answering it arrives; older: keep lane",
        low=0.0, low_inclusive=False)
    max_states: int = param(16, "states kept by stamp while their command is awaited", low=1, high=10_000)
    max_command_wait: float = param(
        0.25, "seconds (wall clock) a lane change may wait for its state (a command can overtake it); then keep lane",
        low=0.0, low_inclusive=False)
    diagnostics_every: int = param(200, "publish safety/diagnostics every this many commands (and at exit)", low=1)
    n_actions: int = param(3, "the scenario's actions (3: keep/left/right; 5: also faster/slower, passed like keep "
                           "lane); der graph --scenario sets it", choices=(3, 5))


#: argument of ``python -m der_ros.graph.composed`` that adds the safety node to the composed graph
SAFETY_FLAG = "--with-safety"

#: agent parameters that may change while the node runs (all others are read-only)
AGENT_MUTABLE = frozenset({"replay.lam", "agent.lr", "checkpoint_every", "metrics_every", "checkpoint_out"})

#: node name -> its parameter sections (prefix -> default config), in the graph's start order
NODE_SECTIONS: dict[str, Callable[[], dict[str, Any]]] = {
    "recorder_node": lambda: {"": RecorderConfig()},
    "agent_node": lambda: {"": AgentNodeConfig(), "agent": DQNConfig(), "replay": ReplayConfig(),
                           "observation": ObservationConfig()},
    "bridge_node": lambda: {"": BridgeNodeConfig(), "scenario": ScenarioConfig()},
    # the shield between agent and bridge (der graph --safety; docs/safety.md): RSS by default
    "safety_node": lambda: {"": SafetyNodeConfig(), "safety": SafetyConfig(kind="rss")},
}


def parameter_sections(node: str) -> dict[str, Any]:
    """Prefix -> default config of every parameter section of ``node`` (a key of :data:`NODE_SECTIONS`)."""
    return NODE_SECTIONS[node]()
