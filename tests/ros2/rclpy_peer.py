"""Real rclpy (Jazzy, the rclpy venv) nodes the ROS 2 tests talk to; never imported by our interpreter.

    python rclpy_peer.py relay TYPE [--qos reliable|best_effort] [--domain N]
        subscribes /uniros_out (TYPE): prints each message as one JSON line {"msg": fields, "cdr": hex of rclpy's
        own serialization}; reads JSON lines {"msg": fields} on stdin and publishes each on /uniros_in (TYPE).
    python rclpy_peer.py codec TYPE
        no network: reads hex lines of CDR on stdin, deserializes them with rclpy, prints {"msg": ..., "cdr": ...}
        (rclpy's serialization of what it read); reads {"msg": fields} lines and prints their serialization.
    python rclpy_peer.py publish TOPIC TYPE [--qos ...]
        publishes a default TYPE on TOPIC at 20 Hz.
    python rclpy_peer.py watch TOPIC
        prints "publishers N" each time the number of publishers on TOPIC (rclpy's graph) changes.

TYPE is sensor_msgs/msg/JointState, std_msgs/msg/Float64MultiArray or trajectory_msgs/msg/JointTrajectory.
Prints ``ready`` once its endpoints are up.
"""

import argparse
import importlib
import json
import sys
import threading

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message


def msg_class(name: str):
    pkg, sub, cls = name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{sub}"), cls)


def to_fields(msg):
    """A message as plain JSON values (nested messages as dicts, arrays as lists)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {k: to_fields(getattr(msg, k)) for k in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or type(msg).__name__ == "array" or hasattr(msg, "tolist"):
        return [to_fields(v) for v in (msg.tolist() if hasattr(msg, "tolist") else msg)]
    return msg


def from_fields(cls, fields):
    msg = cls()
    types = msg.get_fields_and_field_types()
    for k, v in fields.items():
        current = getattr(msg, k)
        if hasattr(current, "get_fields_and_field_types"):
            setattr(msg, k, from_fields(type(current), v))
        elif types[k].startswith("sequence<") and "/" in types[k]:
            inner = types[k][len("sequence<") : -1].split(",")[0]
            pkg, name = inner.split("/")
            sub_cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
            setattr(msg, k, [from_fields(sub_cls, x) for x in v])
        else:
            setattr(msg, k, v)
    return msg


def qos_of(name: str) -> QoSProfile:
    q = QoSProfile(depth=10)
    q.reliability = ReliabilityPolicy.BEST_EFFORT if name == "best_effort" else ReliabilityPolicy.RELIABLE
    return q


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("mode")
    p.add_argument("args", nargs="*")
    p.add_argument("--qos", default="reliable")
    a = p.parse_args()
    if a.mode == "codec":
        cls = msg_class(a.args[0])
        print("ready", flush=True)
        for line in sys.stdin:
            line = line.strip()
            if line.startswith("{"):
                msg = from_fields(cls, json.loads(line)["msg"])
            else:
                msg = deserialize_message(bytes.fromhex(line), cls)
            print(json.dumps({"msg": to_fields(msg), "cdr": serialize_message(msg).hex()}), flush=True)
        return
    rclpy.init()
    node = rclpy.create_node("uniros_test_peer")
    if a.mode == "relay":
        cls = msg_class(a.args[0])
        pub = node.create_publisher(cls, "/uniros_in", qos_of(a.qos))

        def on_msg(msg) -> None:
            print(json.dumps({"msg": to_fields(msg), "cdr": serialize_message(msg).hex()}), flush=True)

        node.create_subscription(cls, "/uniros_out", on_msg, qos_of(a.qos))

        def read_stdin() -> None:
            for line in sys.stdin:
                if line.startswith("{"):
                    pub.publish(from_fields(cls, json.loads(line)["msg"]))

        threading.Thread(target=read_stdin, daemon=True).start()
    elif a.mode == "publish":
        topic, cls = a.args[0], msg_class(a.args[1])
        pub = node.create_publisher(cls, topic, qos_of(a.qos))
        node.create_timer(0.05, lambda: pub.publish(cls()))
    elif a.mode == "watch":
        last = [-1]

        def look() -> None:
            n = node.count_publishers(a.args[0])
            if n != last[0]:
                last[0] = n
                print(f"publishers {n}", flush=True)

        node.create_timer(0.01, look)
    else:
        raise SystemExit(f"unknown mode {a.mode!r}")
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == "__main__":
    main()
