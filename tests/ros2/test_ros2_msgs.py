"""ROS 2 messages (adapters/ros2/msgs.py) against rclpy's own: the same bytes and the same fields, both ways.

rclpy (Jazzy, from the rclpy venv of ``uniros_async.bench.ros2_peers``) runs in its own process as a codec
(``rclpy_peer.py codec``): it reads our CDR and serializes its own, with no network. It runs in the namespace with
the other ROS 2 tests all the same: rclpy's bundled lttng-ust leaves files in /dev/shm, which go with the namespace.
The names, URIs and settings checks below need no peer at all.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _ros_helpers import plain_fields
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uniros_async.errors import CodecError, ConfigError

PEER = Path(__file__).with_name("rclpy_peer.py")
msgs = pytest.importorskip("uniros_async.adapters.ros2.msgs")
pytest.importorskip("cyclonedds", reason="pip install -e '.[ros2]'")
pytest.importorskip("rosbags", reason="pip install -e '.[ros2]'")


@pytest.fixture(scope="module")
def codecs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, subprocess.Popen[str]]]:
    from uniros_async.bench.ros2_peers import kill_process, ros2_missing, skip_or_fail, start_rclpy, wait_for_line

    reason = ros2_missing()
    if reason is not None:
        skip_or_fail(reason)
    tmp = tmp_path_factory.mktemp("ros2_codec")
    procs = {}
    try:
        for t in (
            "sensor_msgs/msg/JointState",
            "std_msgs/msg/Float64MultiArray",
            "trajectory_msgs/msg/JointTrajectory",
        ):
            procs[t] = start_rclpy(PEER, "codec", t, tmp_path=tmp, stdin=True)
        for proc in procs.values():
            wait_for_line(proc, "ready", timeout_s=60.0)
        yield procs
    finally:
        for proc in procs.values():
            kill_process(proc)


def _ask(proc: subprocess.Popen[str], line: str) -> dict[str, Any]:
    from uniros_async.bench.ros2_peers import wait_for_line

    assert proc.stdin is not None
    proc.stdin.write(line + "\n")
    proc.stdin.flush()
    return dict(json.loads(wait_for_line(proc, "{", timeout_s=30.0)))


def _both_ways(codecs: dict[str, subprocess.Popen[str]], ros_type: str, msg: Any) -> None:
    ours = msgs.serialize(msg, ros_type)
    # ours -> rclpy: it reads the fields we sent; its bytes are ours but for what it leaves unset (Fast CDR writes
    # no alignment padding bytes, and adds a few at the end from its size estimate): read back, they are ours
    got = _ask(codecs[ros_type], ours.hex())
    assert got["msg"] == plain_fields(msg)
    theirs = bytes.fromhex(got["cdr"])
    assert len(theirs) >= len(ours)
    back = msgs.deserialize(theirs, ros_type)
    assert plain_fields(back) == plain_fields(msg) and msgs.serialize(back, ros_type) == ours
    # rclpy -> ours: rclpy builds the message from its fields and serializes it; we read the same fields
    built = _ask(codecs[ros_type], json.dumps({"msg": plain_fields(msg)}))
    assert plain_fields(msgs.deserialize(bytes.fromhex(built["cdr"]), ros_type)) == plain_fields(msg)


_text = st.text(st.characters(min_codepoint=1, max_codepoint=0x2FF, blacklist_categories=("Cs",)), max_size=12)
_f64 = st.floats(allow_nan=False, allow_infinity=True, width=64)
_arr = st.lists(_f64, max_size=9)
_stamp = st.tuples(st.integers(-(2**31), 2**31 - 1), st.integers(0, 999_999_999))


def _cls(name: str) -> Any:
    return msgs.message_class(name)


def _header(stamp: tuple[int, int], frame: str) -> Any:
    return _cls("std_msgs/msg/Header")(
        stamp=_cls("builtin_interfaces/msg/Time")(sec=stamp[0], nanosec=stamp[1]), frame_id=frame
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(stamp=_stamp, frame=_text, names=st.lists(_text, max_size=9), pos=_arr, vel=_arr, eff=_arr)
def test_joint_state_matches_rclpy(
    codecs: Any, stamp: Any, frame: str, names: list[str], pos: Any, vel: Any, eff: Any
) -> None:
    msg = _cls("sensor_msgs/msg/JointState")(
        header=_header(stamp, frame),
        name=names,
        position=np.array(pos, float),
        velocity=np.array(vel, float),
        effort=np.array(eff, float),
    )
    _both_ways(codecs, "sensor_msgs/msg/JointState", msg)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    dims=st.lists(st.tuples(_text, st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1)), max_size=3),
    offset=st.integers(0, 2**32 - 1),
    data=_arr,
)
def test_float64_multi_array_matches_rclpy(codecs: Any, dims: Any, offset: int, data: Any) -> None:
    dim = _cls("std_msgs/msg/MultiArrayDimension")
    layout = _cls("std_msgs/msg/MultiArrayLayout")(
        dim=[dim(label=a, size=b, stride=c) for a, b, c in dims], data_offset=offset
    )
    _both_ways(
        codecs,
        "std_msgs/msg/Float64MultiArray",
        _cls("std_msgs/msg/Float64MultiArray")(layout=layout, data=np.array(data, float)),
    )


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    stamp=_stamp,
    names=st.lists(_text, max_size=6),
    points=st.lists(st.tuples(_arr, _arr, _arr, _arr, _stamp), max_size=3),
)
def test_joint_trajectory_matches_rclpy(codecs: Any, stamp: Any, names: list[str], points: Any) -> None:
    point = _cls("trajectory_msgs/msg/JointTrajectoryPoint")
    duration = _cls("builtin_interfaces/msg/Duration")
    pts = [
        point(
            positions=np.array(p, float),
            velocities=np.array(v, float),
            accelerations=np.array(a, float),
            effort=np.array(e, float),
            time_from_start=duration(sec=t[0], nanosec=t[1]),
        )
        for p, v, a, e, t in points
    ]
    msg = _cls("trajectory_msgs/msg/JointTrajectory")(header=_header(stamp, ""), joint_names=names, points=pts)
    _both_ways(codecs, "trajectory_msgs/msg/JointTrajectory", msg)


def test_hashes_match_what_jazzy_announces() -> None:
    """RIHS01 hashes of Jazzy's rosidl (as rclpy's type descriptions give them) for the types the bridge uses."""
    assert msgs.type_hash("sensor_msgs/msg/JointState") == (
        "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
    )
    assert msgs.type_hash("interbotix_xs_msgs/msg/JointGroupCommand").startswith("RIHS01_")
    assert msgs.type_hash("std_msgs/Float64MultiArray") == msgs.type_hash("std_msgs/msg/Float64MultiArray")


def test_names_and_bad_bytes() -> None:
    assert msgs.dds_type_name("sensor_msgs/msg/JointState") == "sensor_msgs::msg::dds_::JointState_"
    assert (
        msgs.dds_type_name("interbotix_xs_msgs/JointGroupCommand")
        == "interbotix_xs_msgs::msg::dds_::JointGroupCommand_"
    )
    assert msgs.ros_type_from_dds("std_msgs::msg::dds_::Float64MultiArray_") == "std_msgs/msg/Float64MultiArray"
    assert msgs.dds_topic_name("/rx200/joint_states") == "rt/rx200/joint_states"
    with pytest.raises(ConfigError, match="absolute ROS 2 topic"):
        msgs.dds_topic_name("rx200/joint_states")
    with pytest.raises(ConfigError, match="unknown ROS 2 message type"):
        msgs.type_hash("my_msgs/msg/Nope")
    with pytest.raises(ConfigError, match="pkg/|like sensor_msgs/msg/JointState"):
        msgs.ros_type_name("JointState")
    with pytest.raises(CodecError, match="sensor_msgs/msg/JointState"):
        msgs.deserialize(b"\x00\x01\x00\x00\xff\xff", "sensor_msgs/msg/JointState")
    with pytest.raises(CodecError, match="encapsulation"):
        msgs.deserialize(b"\x00\x07\x00\x00", "sensor_msgs/msg/JointState")


def test_uris_and_settings() -> None:
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig, parse_ros2_uri

    u = parse_ros2_uri("ros2://3/arm1?driver=forward_position_controller&discovery=subnet&state_timeout_s=2&insecure=1")
    assert (u.domain_id, u.namespace, u.localhost_only) == (3, "/arm1", False)
    assert u.settings == {"driver": "forward_position_controller", "state_timeout_s": 2.0, "insecure": True}
    assert parse_ros2_uri("ros2://").domain_id is None and parse_ros2_uri("ros2://").localhost_only
    for bad, why in (
        ("ros2://x", "domain id"),
        ("ros2://300", "domain id"),
        ("ros2://0?topic=/x", "unknown parameter"),
        ("ros2://0?discovery=wan", "discovery must be"),
        ("tcp://0", "expected a ROS 2 arm"),
    ):
        with pytest.raises(ConfigError, match=why):
            parse_ros2_uri(bad)
    cfg = Ros2BridgeConfig.from_uri("rx200", "ros2://")
    assert (cfg.joint_states, cfg.command, cfg.command_type, cfg.group) == (
        "/rx200/joint_states",
        "/rx200/commands/joint_group",
        "interbotix_xs_msgs/msg/JointGroupCommand",
        "arm",
    )
    moved = Ros2BridgeConfig.from_uri("rx200", "ros2://0/lab/arm2")  # xs_sdk's topics, in another namespace
    assert (moved.joint_states, moved.command) == ("/lab/arm2/joint_states", "/lab/arm2/commands/joint_group")
    ctl = Ros2BridgeConfig.from_uri("rx200", "ros2://0/arm1?driver=forward_position_controller")
    assert (ctl.joint_states, ctl.command, ctl.command_type) == (
        "/arm1/joint_states",
        "/arm1/forward_position_controller/commands",
        "std_msgs/msg/Float64MultiArray",
    )
    assert Ros2BridgeConfig.from_uri("ned2", "ros2://").command == "/joint_trajectory_controller/joint_trajectory"
    with pytest.raises(ConfigError, match="command_type must be one of"):
        Ros2BridgeConfig(robot="rx200", command_type="std_msgs/msg/String")
    with pytest.raises(ConfigError, match="cannot authenticate its peers"):  # the subnet only when asked twice
        Ros2BridgeConfig.from_uri("rx200", "ros2://0?discovery=subnet")
    assert not Ros2BridgeConfig.from_uri("rx200", "ros2://0?discovery=subnet&insecure=1").localhost_only
    with pytest.raises(ConfigError, match="insecure must be"):
        parse_ros2_uri("ros2://0?insecure=yes")
    with pytest.raises(ConfigError, match="did you mean|registered"):
        Ros2BridgeConfig(robot="rx200", driver="xs_skd")
    with pytest.raises(ConfigError, match="unknown setting"):
        Ros2BridgeConfig.from_uri("rx200", "ros2://", topic="/x")
    import gymnasium as gym

    import uniros_async  # noqa: F401

    with pytest.raises(ConfigError, match="unknown parameter"):
        gym.make("uniros/Rx200Reach-v0", robot="ros2://0?topic=/x")
    with pytest.raises(ConfigError, match="ros1 settings"):
        gym.make("uniros/Rx200Reach-v0", robot="ros2://0", ros1={"command": "/x"})


def test_ros_domain_id_is_read_as_rclpy_reads_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from uniros_async.adapters.ros2 import domain_id_from_env
    from uniros_async.adapters.ros2_bridge import Ros2BridgeConfig

    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert domain_id_from_env() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domain_id_from_env() == 42
    assert Ros2BridgeConfig.from_uri("rx200", "ros2://").domain_id is None  # None: the node reads $ROS_DOMAIN_ID
    for bad in ("x", "300", "-1"):
        monkeypatch.setenv("ROS_DOMAIN_ID", bad)
        with pytest.raises(ConfigError, match="ROS_DOMAIN_ID must be an integer in 0..232"):
            domain_id_from_env()
