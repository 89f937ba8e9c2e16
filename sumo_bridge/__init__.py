"""sumo_bridge: the SUMO lane-change scenario (networks, libsumo environment) and its ROS 2 bridge node.

Everything but ``bridge_node`` is ROS-free.
"""
