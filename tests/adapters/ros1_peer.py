"""A real rospy node for the ROS 1 adapter tests; run by the system Python (``ros1_python()``), never imported.

Modes (TYPE like ``sensor_msgs/JointState``; every mode prints ``ready`` once set up, then runs until SIGINT):

- ``echo TYPE IN OUT``: subscribe IN, republish each message on OUT.
- ``talk TYPE TOPIC RATE_HZ``: publish at RATE_HZ; a JointState carries position [i, -i] (rospy sets header.seq).
- ``listen TYPE TOPIC``: subscribe, print ``got <json>`` per message.
- ``anylisten TOPIC``: subscribe with rospy.AnyMsg (md5 ``*``), print ``got <json>`` with type, md5sum and raw hex.
- ``latch TYPE TOPIC``: publish one latched JointState (name ["latched"], position [42.0]).
"""

import importlib
import json
import sys

import genpy
import rospy


def msg_class(type_name):
    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(pkg + ".msg"), name)


def jsonable(value):
    if isinstance(value, genpy.Time | genpy.Duration):
        return value.to_nsec()
    if isinstance(value, genpy.Message):
        return {slot: jsonable(getattr(value, slot)) for slot in value.__slots__}
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    return value


def say(line):
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def make(cls, i):
    msg = cls()
    if cls._type == "sensor_msgs/JointState":
        msg.header.stamp = rospy.Time.now()
        msg.name = ["j1", "j2"]
        msg.position = [float(i), float(-i)]
    elif cls._type == "std_msgs/Float64MultiArray":
        msg.data = [float(i), 0.5]
    return msg


def main(argv):
    mode = argv[0]
    rospy.init_node("uniros_peer_" + mode, anonymous=True, disable_rosout=True)
    if mode == "echo":
        cls = msg_class(argv[1])
        out = rospy.Publisher(argv[3], cls, queue_size=100)
        rospy.Subscriber(argv[2], cls, out.publish, queue_size=100)
    elif mode == "talk":
        cls = msg_class(argv[1])
        pub = rospy.Publisher(argv[2], cls, queue_size=100)
        rate = rospy.Rate(float(argv[3]))
        say("ready")
        i = 0
        while not rospy.is_shutdown():
            i += 1
            pub.publish(make(cls, i))
            try:
                rate.sleep()
            except rospy.ROSInterruptException:
                break
        return
    elif mode == "listen":
        rospy.Subscriber(argv[2], msg_class(argv[1]), lambda m: say("got " + json.dumps(jsonable(m))))
    elif mode == "anylisten":

        def on_any(m):
            header = m._connection_header
            say("got " + json.dumps({"type": header["type"], "md5sum": header["md5sum"], "hex": m._buff.hex()}))

        rospy.Subscriber(argv[1], rospy.AnyMsg, on_any)
    elif mode == "latch":
        cls = msg_class(argv[1])
        pub = rospy.Publisher(argv[2], cls, queue_size=1, latch=True)
        msg = cls()
        msg.name = ["latched"]
        msg.position = [42.0]
        pub.publish(msg)
    else:
        raise SystemExit("unknown mode " + mode)
    say("ready")
    rospy.spin()


if __name__ == "__main__":
    main(sys.argv[1:])
