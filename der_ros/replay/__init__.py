"""ROS-free replay core: uniform (DQN), prioritized (PER) and double experience replay (DER).

``make_replay(cfg, obs_shape, obs_dtype, batch_size, seed)`` builds the buffer a
:class:`ReplayConfig` asks for; every buffer has the :class:`ReplayBuffer` interface and
returns :class:`Batch` tuples. ``load_replay(path)`` restores one saved with ``save``.
"""

from der_ros.replay.base import Batch, ReplayBuffer
from der_ros.replay.config import ReplayConfig
from der_ros.replay.double_replay import DoubleReplay
from der_ros.replay.factory import REPLAY_KINDS, load_replay, make_replay
from der_ros.replay.prioritized import PrioritizedReplay
from der_ros.replay.storage import ReplayMemoryError, RingStorage, storage_bytes
from der_ros.replay.sum_tree import SumTree
from der_ros.replay.uniform import UniformReplay

__all__ = [
    "Batch",
    "ReplayBuffer",
    "ReplayConfig",
    "UniformReplay",
    "PrioritizedReplay",
    "DoubleReplay",
    "SumTree",
    "RingStorage",
    "ReplayMemoryError",
    "storage_bytes",
    "make_replay",
    "load_replay",
    "REPLAY_KINDS",
]
