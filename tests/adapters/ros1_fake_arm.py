"""A stand-in for a real arm's ROS 1 driver, run with real rospy by the Debian ``python3`` (not our interpreter).

There is no physical arm here, so this node plays the driver's part on a real ROS graph: it publishes
``sensor_msgs/JointState`` at the hardware rate and moves its joints toward the newest command received on the
driver's command topic (``interbotix_xs_msgs/JointGroupCommand``, ``trajectory_msgs/JointTrajectory`` or
``std_msgs/Float64MultiArray``), at most ``--speed`` rad/s per joint. Every command received is printed on stdout
as one JSON line (``{"type": ..., "positions": [...], ...}``) for the test to check; ``ready`` is printed once
both topics are set up.

The Interbotix message is not in Debian, so it is declared here as genpy would generate it (same type name, md5sum
and definition); for the other types the Debian classes are used.

    python3 ros1_fake_arm.py --joints waist,shoulder,elbow,wrist_angle,wrist_rotate,gripper,left_finger,right_finger \
        --arm 5 --joint-states /rx200/joint_states --command /rx200/commands/joint_group \
        --command-type interbotix_xs_msgs/JointGroupCommand --rate 10
"""

import argparse
import json
import struct
import sys
import threading

import genpy
import rospy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory


class JointGroupCommand(genpy.Message):
    """interbotix_xs_msgs/JointGroupCommand (string name, float32[] cmd), written out by hand."""

    _md5sum = "ARG_MD5"
    _type = "interbotix_xs_msgs/JointGroupCommand"
    _has_header = False
    _full_text = "string name\nfloat32[] cmd\n"
    __slots__ = ["name", "cmd"]
    _slot_types = ["string", "float32[]"]

    def __init__(self, *args, **kwds):
        super().__init__(*args, **kwds)
        if self.name is None:
            self.name = ""
        if self.cmd is None:
            self.cmd = []

    def _get_types(self):
        return self._slot_types

    def serialize(self, buff):
        name = self.name.encode("utf-8")
        buff.write(struct.pack(f"<I{len(name)}s", len(name), name))
        buff.write(struct.pack(f"<I{len(self.cmd)}f", len(self.cmd), *self.cmd))

    def deserialize(self, str_):
        (n,) = struct.unpack_from("<I", str_, 0)
        self.name = bytes(str_[4 : 4 + n]).decode("utf-8")
        off = 4 + n
        (k,) = struct.unpack_from("<I", str_, off)
        self.cmd = list(struct.unpack_from(f"<{k}f", str_, off + 4))
        return self


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--joints", required=True, help="comma-separated joint_states names, arm joints first")
    ap.add_argument("--arm", type=int, required=True, help="how many of them the command moves")
    ap.add_argument("--joint-states", required=True)
    ap.add_argument("--command", required=True)
    ap.add_argument("--command-type", required=True)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--speed", type=float, default=1.0, help="rad/s per joint")
    ap.add_argument("--md5", default="", help="md5sum of the Interbotix message")
    ap.add_argument("--drop-joint", default="", help="leave this joint out of the joint states")
    args = ap.parse_args()
    JointGroupCommand._md5sum = args.md5 or "*"
    names = args.joints.split(",")
    q = [0.0] * len(names)
    target = list(q)
    lock = threading.Lock()
    cls = {
        "interbotix_xs_msgs/JointGroupCommand": JointGroupCommand,
        "trajectory_msgs/JointTrajectory": JointTrajectory,
        "std_msgs/Float64MultiArray": Float64MultiArray,
    }[args.command_type]

    def on_command(msg):
        if args.command_type == "interbotix_xs_msgs/JointGroupCommand":
            pos, extra = list(msg.cmd), {"group": msg.name}
        elif args.command_type == "trajectory_msgs/JointTrajectory":
            pt = msg.points[-1]
            pos = list(pt.positions)
            extra = {"joint_names": list(msg.joint_names), "time_from_start_s": pt.time_from_start.to_sec()}
        else:
            pos, extra = list(msg.data), {}
        with lock:
            target[: len(pos)] = pos[: args.arm]
        print(json.dumps({"type": args.command_type, "positions": pos, **extra}), flush=True)

    rospy.init_node("fake_arm_driver", disable_signals=True)
    pub = rospy.Publisher(args.joint_states, JointState, queue_size=1)
    rospy.Subscriber(args.command, cls, on_command, queue_size=1)
    print("ready", flush=True)
    rate = rospy.Rate(args.rate)
    step = args.speed / args.rate
    vel = [0.0] * len(names)
    keep = [i for i, n in enumerate(names) if n != args.drop_joint]
    while not rospy.is_shutdown():
        with lock:
            for i in range(args.arm):
                d = max(-step, min(step, target[i] - q[i]))
                q[i] += d
                vel[i] = d * args.rate
        msg = JointState()
        msg.header.stamp = rospy.Time.now()
        msg.name = [names[i] for i in keep]
        msg.position = [q[i] for i in keep]
        msg.velocity = [vel[i] for i in keep]
        msg.effort = []
        pub.publish(msg)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    sys.exit(main())
