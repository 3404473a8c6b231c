"""A real rospy subscriber at the arm's side of the link, for test_ros1_stale_commands.py; run by the system Python
(``ros1_python()``), never imported.

``ros1_command_recorder.py TOPIC``: subscribes to TOPIC with ``rospy.AnyMsg`` (an Interbotix
``interbotix_xs_msgs/JointGroupCommand``, whose Python class Debian does not ship), decodes each message by hand
(``string name``, ``float32[] cmd``) and prints ``{"ev": "arrived", "t_ns": ..., "seq": ...}`` per message, ``seq``
being ``round(cmd[0] / 0.001) % 1000`` (``netfault.command_position``), with ``time.monotonic_ns()``, the clock the
commander's lines share across namespaces. Prints ``ready`` once subscribed, then runs until SIGINT.
"""

import json
import struct
import sys
import time

import rospy

WAIST_STEP_RAD = 0.001


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def on_command(msg):
    t_ns = time.monotonic_ns()
    buf = msg._buff
    (n_name,) = struct.unpack_from("<I", buf, 0)
    pos = 4 + n_name
    (n_cmd,) = struct.unpack_from("<I", buf, pos)
    cmd = struct.unpack_from(f"<{n_cmd}f", buf, pos + 4)
    say(json.dumps({"ev": "arrived", "t_ns": t_ns, "seq": round(cmd[0] / WAIST_STEP_RAD) % 1000}))


def main(argv):
    rospy.init_node("uniros_command_recorder", anonymous=True, disable_rosout=True)
    rospy.Subscriber(argv[0], rospy.AnyMsg, on_command, queue_size=1000)
    say("ready")
    rospy.spin()


if __name__ == "__main__":
    main(sys.argv[1:])
