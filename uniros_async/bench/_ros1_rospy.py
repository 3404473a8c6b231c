"""The rospy side of ``uniros bench ros1``: run by the system Python that has ROS 1 (never imported by our code).

    python3 _ros1_rospy.py echo     # /uniros_ping -> /uniros_pong and /rospy_ping -> /rospy_pong
    python3 _ros1_rospy.py client   # reads "go N" lines on stdin; for each, N round trips over /rospy_ping,
                                    # printing one JSON line: the round trips in ns (_peer_loop.py)

rospy at its fastest: publishers without a queue (``publish`` writes in the caller's thread), subscribers with
``tcp_nodelay``. Prints ``ready`` once its topics are set up.
"""

import sys
import threading
import time
from typing import TYPE_CHECKING

import rospy
from sensor_msgs.msg import JointState

if TYPE_CHECKING:
    from uniros_async.bench._peer_loop import answer_go_lines
else:  # run as a script by an interpreter without our package: the module beside this file
    from _peer_loop import answer_go_lines

NAMES = ["waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate", "gripper", "left_finger", "right_finger"]


def echo() -> None:
    rospy.init_node("uniros_bench_echo", disable_signals=True)
    keep = []
    for who in ("uniros", "rospy"):
        pub = rospy.Publisher(f"/{who}_pong", JointState, queue_size=None)
        keep.append(pub)
        keep.append(rospy.Subscriber(f"/{who}_ping", JointState, pub.publish, tcp_nodelay=True))
    print("ready", flush=True)
    while not rospy.is_shutdown():
        time.sleep(0.5)


def client() -> None:
    rospy.init_node("uniros_bench_rospy_client", disable_signals=True)
    got = threading.Event()
    want = [""]

    def on_pong(msg: JointState) -> None:
        if msg.header.frame_id == want[0]:  # the token: rospy's publishers renumber header.seq
            got.set()

    pub = rospy.Publisher("/rospy_ping", JointState, queue_size=None)
    rospy.Subscriber("/rospy_pong", JointState, on_pong, tcp_nodelay=True)
    msg = JointState(name=NAMES, position=[0.1] * 8, velocity=[0.0] * 8, effort=[0.0] * 8)

    def arm(token: str) -> None:
        want[0] = msg.header.frame_id = token
        got.clear()

    def round_trip() -> bool:
        pub.publish(msg)
        return got.wait(2.0)

    print("ready", flush=True)
    answer_go_lines(arm, round_trip)


if __name__ == "__main__":
    {"echo": echo, "client": client}[sys.argv[1]]()
