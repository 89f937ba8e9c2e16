"""ROS-free rosbag2 MCAP files: the writer, the streamed reader and the record layer under them.

What the messages in a bag mean is :mod:`der_ros.contract`; the tools that read bags as episodes
(export, plots, rendering, ``der bag``) are :mod:`der_ros.offline`. Kept import-light on purpose:
import the submodule you need (``der_ros.bag.reader``, ...).
"""
