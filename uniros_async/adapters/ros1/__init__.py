"""A pure-asyncio ROS 1 client: drive arms whose drivers are ROS 1 nodes, with no rospy in our process.

``open_ros1_node`` (node.py) registers with a rosmaster and speaks TCPROS; msgs.py holds the messages the arm
drivers use (JointState, Float64MultiArray, JointTrajectory, Interbotix JointGroupCommand) in ROS 1 wire format.
Names load lazily: ``import uniros_async.adapters.ros1`` alone imports neither.
"""

from uniros_async._lazy import lazy_exports

__all__ = [
    "MESSAGE_TYPES",
    "Float64MultiArray",
    "JointGroupCommand",
    "JointState",
    "JointTrajectory",
    "JointTrajectoryPoint",
    "Ros1Message",
    "Ros1Node",
    "Ros1Publisher",
    "Ros1Subscriber",
    "RosHeader",
    "open_ros1_node",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(
            [
                "MESSAGE_TYPES",
                "Float64MultiArray",
                "JointGroupCommand",
                "JointState",
                "JointTrajectory",
                "JointTrajectoryPoint",
                "Ros1Message",
                "RosHeader",
            ],
            "msgs",
        ),
        **dict.fromkeys(["Ros1Node", "Ros1Publisher", "Ros1Subscriber", "open_ros1_node"], "node"),
    },
)
