"""A safety layer in front of the lane-change agent (docs/safety.md), ROS-free.

One concept per file: :mod:`.config` (the typed settings), :mod:`.rss` (the RSS longitudinal safe
distance), :mod:`.checker` (which actions are safe, from the ego and its neighbour slots),
:mod:`.sumo_check` (SUMO's own lane-change verdict, where the simulation is at hand),
:mod:`.apply` (replace and mask), :mod:`.observation_mask` (the RSS mask recomputed from stored
observations, for the learner's target) and :mod:`.wrapper` (the gymnasium wrapper). The ROS node
``der_ros/nodes/safety_node.py`` is a thin adapter on these.
"""

from der_ros.safety.apply import KEEP, masked_argmax, replace_unsafe
from der_ros.safety.checker import RssChecker
from der_ros.safety.config import SAFETY_KINDS, SAFETY_MODES, SafetyConfig
from der_ros.safety.rss import safe_longitudinal_distance

__all__ = [
    "KEEP",
    "SAFETY_KINDS",
    "SAFETY_MODES",
    "RssChecker",
    "SafetyConfig",
    "masked_argmax",
    "replace_unsafe",
    "safe_longitudinal_distance",
]
