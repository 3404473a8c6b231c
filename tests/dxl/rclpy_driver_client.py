"""A real rclpy (Jazzy, the rclpy venv) client of an arm's ROS 2 driver; never imported by our interpreter.

    python rclpy_driver_client.py JOINT_STATES COMMAND
        subscribes JOINT_STATES (sensor_msgs/msg/JointState) and prints each message as one JSON line
        {"name": [...], "position": [...], "velocity": [...], "stamp": [sec, nanosec]}; reads JSON lines
        {"data": [...]} on stdin and publishes each on COMMAND as a std_msgs/msg/Float64MultiArray. Both reliable
        with keep last 10, as ros2_control's joint_state_broadcaster and forward_position_controller.

Prints ``ready`` once its endpoints are up.
"""

import json
import sys
import threading

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray


def main() -> None:
    joint_states, command = sys.argv[1], sys.argv[2]
    rclpy.init()
    node = rclpy.create_node("uniros_test_driver_client")
    qos = QoSProfile(depth=10)
    qos.reliability = ReliabilityPolicy.RELIABLE
    pub = node.create_publisher(Float64MultiArray, command, qos)

    def on_state(msg: JointState) -> None:
        line = {
            "name": list(msg.name),
            "position": list(msg.position),
            "velocity": list(msg.velocity),
            "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
        }
        print(json.dumps(line), flush=True)

    node.create_subscription(JointState, joint_states, on_state, qos)

    def read_stdin() -> None:
        for line in sys.stdin:
            if line.startswith("{"):
                pub.publish(Float64MultiArray(data=[float(v) for v in json.loads(line)["data"]]))

    threading.Thread(target=read_stdin, daemon=True).start()
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == "__main__":
    main()
