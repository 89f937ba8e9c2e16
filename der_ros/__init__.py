"""der_ros: Double Experience Replay (DER) DQN agents for SUMO lane changing, with ROS 2 nodes.

The core (``der_ros.replay``, ``der_ros.agent``, ``der_ros.train``, ``der_ros.bag``) never
imports ROS; node adapters live in ``*_node.py`` modules.
"""

__version__ = "0.1.0"
