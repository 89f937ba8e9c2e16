"""``der graph``: run the ROS 2 graph (SUMO bridge, DER agent, MCAP recorder) as supervised processes.

``graph_cli`` (arguments, the run) starts the nodes with the params file that
:func:`der_ros.nodes.params.build_graph_params` assembles; ``runner`` is the ROS-free process
supervisor, ``monitor`` a small rclpy node that counts progress, ``progress`` shows it, ``report``
writes the summary at the end; ``composed`` runs the three nodes in one process.
"""
