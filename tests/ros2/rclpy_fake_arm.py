"""A stand-in for a ros2_control arm's driver, run with real rclpy (Jazzy, the rclpy venv), not our interpreter.

There is no physical arm here, so this node plays the driver's part on a real ROS 2 graph: it publishes
``sensor_msgs/msg/JointState`` at the hardware rate (reliable, keep last 10, as joint_state_broadcaster does) and
moves its joints toward the newest command on the controller's topic (``std_msgs/msg/Float64MultiArray`` of a
forward_position_controller or ``trajectory_msgs/msg/JointTrajectory`` of a joint_trajectory_controller), at most
``--speed`` rad/s per joint. Every command received is printed as one JSON line (``{"type": ..., "positions":
[...], ...}``); ``ready`` once both endpoints are up. The Interbotix message is not on PyPI, so the xs_sdk path is
tested against our own mirror instead (test_ros2_driver.py).

    python rclpy_fake_arm.py --joints waist,shoulder,elbow,wrist_angle,wrist_rotate,gripper,left_finger,right_finger \
        --arm 5 --joint-states /joint_states --command /forward_position_controller/commands \
        --command-type std_msgs/msg/Float64MultiArray --rate 10
"""

import argparse
import json

import rclpy
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--joints", required=True)
    p.add_argument("--arm", type=int, required=True)
    p.add_argument("--joint-states", required=True)
    p.add_argument("--command", required=True)
    p.add_argument("--command-type", required=True)
    p.add_argument("--rate", type=float, default=10.0)
    p.add_argument("--speed", type=float, default=1.0)
    args = p.parse_args()
    names = args.joints.split(",")
    q = [0.0] * len(names)
    target = list(q[: args.arm])

    rclpy.init()
    node = rclpy.create_node("uniros_fake_arm")
    qos = QoSProfile(depth=10)
    pub = node.create_publisher(JointState, args.joint_states, qos)

    def on_command(msg) -> None:
        if args.command_type.endswith("Float64MultiArray"):
            target[:] = list(msg.data)
            out = {"type": "std_msgs/msg/Float64MultiArray", "positions": list(msg.data)}
        else:
            point = msg.points[-1]
            where = {n: i for i, n in enumerate(msg.joint_names)}
            target[:] = [point.positions[where[n]] for n in names[: args.arm]]
            out = {
                "type": "trajectory_msgs/msg/JointTrajectory",
                "joint_names": list(msg.joint_names),
                "positions": list(point.positions),
                "time_from_start_s": point.time_from_start.sec + point.time_from_start.nanosec / 1e9,
            }
        print(json.dumps(out), flush=True)

    cls = Float64MultiArray if args.command_type.endswith("Float64MultiArray") else JointTrajectory
    node.create_subscription(cls, args.command, on_command, qos)
    step = args.speed / args.rate

    def tick() -> None:
        for i, t in enumerate(target):
            q[i] += max(-step, min(step, t - q[i]))
        msg = JointState(name=names, position=q, velocity=[0.0] * len(q), effort=[0.0] * len(q))
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)

    node.create_timer(1.0 / args.rate, tick)
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == "__main__":
    main()
