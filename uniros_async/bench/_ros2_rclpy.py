"""The rclpy side of ``uniros bench ros2``: run by the rclpy venv's Python (never imported by our code).

    python _ros2_rclpy.py echo     # /uniros_ping -> /uniros_pong and /rclpy_ping -> /rclpy_pong
    python _ros2_rclpy.py client   # reads "go N" lines on stdin; for each, N round trips over /rclpy_ping,
                                   # printing one JSON line: the round trips in ns (_peer_loop.py)
    python _ros2_rclpy.py image_client H W ENC  # the same with sensor_msgs/Image frames (H x W, ENC: rgb8 or
                                   # mono8) over /rclpy_image_ping -> /rclpy_image_pong (uniros bench transport)

rclpy at its fastest for one message at a time: the client publishes, then spins its own single-threaded
executor once per wake-up until the echo is back (no executor thread to hand over to). Both topics use ROS's
default profile (reliable, keep last 10). Prints ``ready`` once its endpoints are up.
"""

import sys
import time
from typing import TYPE_CHECKING

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image, JointState

if TYPE_CHECKING:
    from uniros_async.bench._peer_loop import answer_go_lines
else:  # run as a script by the rclpy venv's Python, without our package: the module beside this file
    from _peer_loop import answer_go_lines

NAMES = ["waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper", "left_finger", "right_finger"]
QOS = QoSProfile(depth=10)


def echo() -> None:
    rclpy.init()
    node = rclpy.create_node("uniros_bench_echo")
    for who in ("uniros", "rclpy"):
        pub = node.create_publisher(JointState, f"/{who}_pong", QOS)
        node.create_subscription(JointState, f"/{who}_ping", pub.publish, QOS)
    image_pub = node.create_publisher(Image, "/rclpy_image_pong", QOS)
    node.create_subscription(Image, "/rclpy_image_ping", image_pub.publish, QOS)
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


def _answer_round_trips(name: str, msg_type: type, ping: str, pong: str, msg: object) -> None:
    """Time round trips of ``msg`` over ``ping`` -> ``pong``, one at a time, as ``_peer_loop`` asks on stdin."""
    rclpy.init()
    node = rclpy.create_node(name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    want = [""]
    got = [False]

    def on_pong(reply: object) -> None:
        if reply.header.frame_id == want[0]:  # type: ignore[attr-defined]
            got[0] = True

    pub = node.create_publisher(msg_type, ping, QOS)
    node.create_subscription(msg_type, pong, on_pong, QOS)

    def arm(token: str) -> None:
        want[0] = msg.header.frame_id = token  # type: ignore[attr-defined]
        got[0] = False

    def round_trip() -> bool:
        pub.publish(msg)
        deadline = time.monotonic() + 2.0
        while not got[0] and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=2.0)
        return got[0]

    print("ready", flush=True)
    answer_go_lines(arm, round_trip)


def client() -> None:
    msg = JointState(name=NAMES, position=[0.1] * 8, velocity=[0.0] * 8, effort=[0.0] * 8)
    _answer_round_trips("uniros_bench_rclpy_client", JointState, "/rclpy_ping", "/rclpy_pong", msg)


def image_client() -> None:
    height, width, encoding = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    step = width * {"rgb8": 3, "mono8": 1}[encoding]
    msg = Image(height=height, width=width, encoding=encoding, step=step, data=bytes(height * step))
    _answer_round_trips("uniros_bench_rclpy_image_client", Image, "/rclpy_image_ping", "/rclpy_image_pong", msg)


if __name__ == "__main__":
    {"echo": echo, "client": client, "image_client": image_client}[sys.argv[1]]()
