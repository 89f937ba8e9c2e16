"""ROS 2 node adapters (rclpy): thin layers over the ROS-free cores.

``params`` binds config dataclasses to node parameters, ``msg_conversions`` turns core data into
messages and back; ``agent_node`` and ``recorder_node`` are the node executables (the bridge node
lives in :mod:`sumo_bridge.bridge_node`). Importing this package does not import rclpy.
"""
