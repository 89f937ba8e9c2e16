"""``der graph``: run the ROS 2 graph (SUMO bridge, DER agent, MCAP recorder) as supervised processes.

``runner`` is the ROS-free process supervisor; ``graph_cli`` builds the node commands, watches
progress through a small rclpy monitor (``monitor``) and prints the summary.
"""
