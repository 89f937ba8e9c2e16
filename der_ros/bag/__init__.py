"""ROS-free rosbag2 MCAP tools: writer, streamed reader, episodes, export, plots, ``der replay``.

Kept import-light on purpose: import the submodule you need (``der_ros.bag.reader``, ...).
"""
