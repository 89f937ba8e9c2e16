"""der_ros: Double Experience Replay (DER) DQN agents for SUMO lane changing, with ROS 2 nodes.

The cores (``replay``, ``agent``, ``train``, ``experiments``, ``bag`` but ``bag.play``, ``sumo_bridge``) never
import ROS; the graph contract every part speaks is ``der_ros.contract``; node adapters live in
``der_ros.nodes`` (``*_node.py``). Layers and rules: ``docs/architecture.md``.
"""

__version__ = "0.1.0"
