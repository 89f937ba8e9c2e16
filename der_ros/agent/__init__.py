"""ROS-free DQN learner (paper section 2.1): config, networks, epsilon schedule, agent."""

from der_ros.agent.config import DQNConfig
from der_ros.agent.dqn import DQNAgent, read_checkpoint, resolve_device
from der_ros.agent.networks import AtariCNN, MLPQNetwork, flatten_parameters, make_q_network
from der_ros.agent.optim import FlatAdam
from der_ros.agent.schedules import LinearSchedule

__all__ = [
    "DQNConfig",
    "DQNAgent",
    "read_checkpoint",
    "resolve_device",
    "AtariCNN",
    "MLPQNetwork",
    "make_q_network",
    "flatten_parameters",
    "FlatAdam",
    "LinearSchedule",
]
