"""A ROS 2 participant with no ROS install: drive arms whose drivers are ROS 2 nodes, with no rclpy in our process.

``open_ros2_node`` (node.py) is one DDS participant (cyclonedds) speaking ROS 2's naming, QoS profiles and type
hashes; msgs.py holds the messages (rosbags' ROS 2 Jazzy store, plus the Interbotix JointGroupCommand) and their CDR.
Names load lazily: ``import uniros_async.adapters.ros2`` alone imports neither cyclonedds nor rosbags.
"""

from uniros_async._lazy import lazy_exports

__all__ = [
    "COMMANDS",
    "SENSOR_DATA",
    "Endpoint",
    "Ros2Node",
    "Ros2Publisher",
    "Ros2Qos",
    "Ros2Subscription",
    "domain_id_from_env",
    "open_ros2_node",
]

__getattr__, __dir__ = lazy_exports(__name__, dict.fromkeys(__all__, "node"))
