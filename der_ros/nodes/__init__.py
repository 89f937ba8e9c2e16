"""ROS 2 node adapters (rclpy): thin layers over the ROS-free cores.

``params`` binds config dataclasses to node parameters, ``msg_conversions`` turns core data into
messages; ``bridge_node``, ``agent_node`` and ``recorder_node`` are the node executables, ``spin``
and ``orphans`` their process life cycle. Importing this package does not import rclpy.
"""
