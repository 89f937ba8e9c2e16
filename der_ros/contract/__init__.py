"""The ROS 2 graph contract, bytes included: what every topic is called, its QoS, and how each message is laid out.

One package, one home: the nodes, the ``der graph`` monitor, the MCAP recorder and the offline tools
take topic names, QoS, status names and the layouts of the messages from here. ROS-free: the parsers
read attributes only (rclpy and rosbags messages alike), the encoders and readers work on plain-CDR
bytes. The rclpy side (QoS profiles, message classes) is :mod:`der_ros.contract_ros`.

Modules (each message's layout is spelled in exactly one of them: parser, CDR encoder and CDR reader
side by side):

* :mod:`~der_ros.contract.topics` -- topic names, status names, QoS, the topic table
* :mod:`~der_ros.contract.cdr` -- plain-CDR primitives, the header, ``/clock``
* :mod:`~der_ros.contract.state` -- ``state`` (PointCloud2)
* :mod:`~der_ros.contract.reward` -- ``reward`` (Vector3Stamped, the applied action in its frame_id)
* :mod:`~der_ros.contract.command` -- ``lane_change_cmd`` (Joy)
* :mod:`~der_ros.contract.odometry` -- ``ego/odom`` (Odometry)
* :mod:`~der_ros.contract.tf` -- ``/tf`` (TFMessage: ``map -> ego``)
* :mod:`~der_ros.contract.events` -- ``episode`` and ``agent/metrics`` key/values (DiagnosticArray)
* :mod:`~der_ros.contract.scene` -- ``scene/vehicles``, ``scene/road`` (MarkerArray)

Every public name is re-exported here: ``from der_ros.contract import STATE, state_cdr, parse_reward``.
"""

from der_ros.contract import command, events, odometry, reward, scene, state, tf, topics
from der_ros.contract.cdr import FLOAT32_MAX, clock_cdr, header_ns, stamp_to_ns
from der_ros.contract.command import *  # noqa: F401,F403
from der_ros.contract.events import *  # noqa: F401,F403
from der_ros.contract.odometry import *  # noqa: F401,F403
from der_ros.contract.reward import *  # noqa: F401,F403
from der_ros.contract.scene import *  # noqa: F401,F403
from der_ros.contract.state import *  # noqa: F401,F403
from der_ros.contract.tf import *  # noqa: F401,F403
from der_ros.contract.topics import *  # noqa: F401,F403

__all__ = [
    "FLOAT32_MAX", "clock_cdr", "header_ns", "stamp_to_ns",
    *topics.__all__, *state.__all__, *reward.__all__, *command.__all__, *odometry.__all__, *events.__all__,
    *scene.__all__, *tf.__all__,
]  # fmt: skip

