"""The ROS 2 graph contract, bytes included: what every topic is called, its QoS, and how its messages are laid out.

One package, one home (issue 13, issue 42): the nodes, the ``der graph`` monitor, the MCAP recorder
and the offline tools all take topic names, QoS, status names and the byte layouts of the messages
from here. ROS-free: the parsers read attributes only (rclpy and rosbags messages alike), and the
encoders/decoders work on plain-CDR bytes. The rclpy side (QoS profiles, message classes) is
:mod:`der_ros.contract_ros`.

Modules: :mod:`~der_ros.contract.topics` (names, QoS, the topic table, message parsers),
:mod:`~der_ros.contract.cdr` (plain-CDR primitives), :mod:`~der_ros.contract.step_cdr` /
:mod:`~der_ros.contract.step_cdr_read` (the per-step messages as bytes and back),
:mod:`~der_ros.contract.scene` (the scene markers as bytes). Every public name is re-exported here,
so ``from der_ros.contract import STATE, state_cdr`` works.
"""

from der_ros.contract.scene import *  # noqa: F401,F403
from der_ros.contract.scene import __all__ as _scene_all
from der_ros.contract.step_cdr import *  # noqa: F401,F403
from der_ros.contract.step_cdr import __all__ as _step_all
from der_ros.contract.step_cdr_read import *  # noqa: F401,F403
from der_ros.contract.step_cdr_read import __all__ as _read_all
from der_ros.contract.topics import *  # noqa: F401,F403
from der_ros.contract.topics import __all__ as _topics_all

__all__ = [*_topics_all, *_step_all, *_read_all, *_scene_all]
