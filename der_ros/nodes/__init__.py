"""ROS 2 node adapters (rclpy): thin layers over the ROS-free cores.

``node_configs`` holds each node's parameter sections (ROS-free), ``params`` binds them to node
parameters (and assembles a graph's params file), ``msg_conversions`` builds the contract's
messages; ``bridge_node``, ``agent_node`` and ``recorder_node`` are the node executables, ``spin``
and ``orphans`` their process life cycle. Importing this package does not import rclpy.
"""
